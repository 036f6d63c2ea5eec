"""Table I's maze rows at the paper's budget: table, per-seed ends and curves from paper_budget.py's runs.

    python experiments/paper_budget_report.py [OUT]      # default experiments/results/paper_budget

Reads every cell of `paper_budget.QUEUE` found in OUT (finished grids and ones
still training, whose rows so far count), and writes OUT/table.md, OUT/table.csv
and OUT/curves_<domain>.png. Success is the paper's: the mean evaluation success
of the last 10 epochs. Per cell: mean and IQM over seeds with 95 % stratified-
bootstrap intervals (`ccp_jax.stats`), per-seed values, first success, the peak of
the 10-epoch running success and the drop from it to the end (the paper's
"Naive decays"), where the last evaluations end, and the probability that CSAC
at our ratio beats each baseline on a seed.
"""
from __future__ import annotations

import csv
import dataclasses
import io
import sys
from pathlib import Path
from typing import Optional

import numpy as np

from ccp_jax import outputs, stats
from common import ALGO_NAMES, PAPER_TABLE1, RESULTS, improvement, rows_by_member, with_interval, write_text
from paper_budget import QUEUE, SEEDS, Cell, cell_grids

# Epochs in the final-success mean (the paper's, as in summary.json) and in the running success.
WINDOW = outputs.FINAL_WINDOW


@dataclasses.dataclass
class Member:
    """One seed's run of a cell: its curve and where its last evaluations end."""

    seed: int
    steps: np.ndarray  # [epochs] env steps
    success: np.ndarray  # [epochs] evaluation success
    stage: np.ndarray  # [epochs] 1-based stage the evaluation episodes end in, mean
    pocket: Optional[np.ndarray]  # [epochs] fraction ending in a dead-end pocket

    @property
    def final(self) -> float:
        return float(np.mean(self.success[-WINDOW:]))

    @property
    def first_success(self) -> Optional[int]:
        hit = np.flatnonzero(self.success > 0)
        return int(self.steps[hit[0]]) if hit.size else None

    @property
    def solved_at(self) -> Optional[int]:
        """Env steps at which the running success first reaches 0.5 (the task learnt), None if never."""
        hit = np.flatnonzero(self.running >= 0.5)
        return int(self.steps[hit[0] + WINDOW - 1]) if hit.size else None

    @property
    def running(self) -> np.ndarray:
        """[epochs − WINDOW + 1] the success averaged over each WINDOW consecutive epochs."""
        return np.convolve(self.success, np.ones(WINDOW) / WINDOW, mode="valid")

    def end(self) -> str:
        stage = np.mean(self.stage[-WINDOW:])
        pocket = "" if self.pocket is None else f", {np.mean(self.pocket[-WINDOW:]):.0%} pocket"
        return f"{self.seed}: room {stage:.1f}{pocket}"


def load_cell(out: Path, cell: Cell) -> list[Member]:
    """Every seed of `cell` found in its folder and its seed-chunk folders, complete epochs only."""
    members = {}
    for folder in cell_grids(out / cell.domain, cell.name):
        if not outputs.metrics_file(folder).exists():
            continue
        for rows in rows_by_member(folder, field="out", complete_epochs=True).values():
            pockets = [r.get("eval_end", {}).get("pocket") for r in rows]
            members[rows[0]["seed"]] = Member(
                seed=rows[0]["seed"], steps=np.array([r["env_steps"] for r in rows]),
                success=np.array([r["success_rate"] for r in rows]),
                stage=1.0 + np.array([r["stage_reached_mean"] for r in rows]),
                pocket=None if None in pockets else np.array(pockets))
    return [members[s] for s in sorted(members)]


def label(cell: Cell) -> str:
    if cell.algo != "csac":
        return ALGO_NAMES[cell.algo]
    return "CSAC η = " + ", ".join(f"{e:g}" for e in cell.etas[0])


def paper_value(cell: Cell) -> Optional[float]:
    if cell.algo != "csac":
        return PAPER_TABLE1[cell.algo][cell.domain]
    eta = cell.etas[0]
    return PAPER_TABLE1["csac"][eta[0]][cell.domain] if len(eta) == 1 else None


def cell_row(cell: Cell, members: list[Member]) -> dict:
    finals = [m.final for m in members]
    firsts = [m.first_success for m in members]
    peaks = [float(m.running.max()) if m.running.size else float("nan") for m in members]
    return dict(domain=cell.domain, method=label(cell), cell=cell.key, seeds=len(members),
                env_steps=int(min(m.steps[-1] for m in members)), finals=finals,
                mean=with_interval(finals, stats.mean), iqm=with_interval(finals, stats.iqm),
                solved=sum(f >= 0.5 for f in finals), first=firsts,
                solved_at=[m.solved_at for m in members],
                peak=peaks, drop=[p - f for p, f in zip(peaks, finals)],
                ends="; ".join(m.end() for m in members), paper=paper_value(cell))


def improvement_lines(found: dict[Cell, list[Member]]) -> list[str]:
    """P(CSAC at our ratio beats the baseline on a seed), per domain, with its 95 % interval."""
    lines = []
    for domain in dict.fromkeys(c.domain for c in found):
        cells = [c for c in found if c.domain == domain]
        ours = next((c for c in cells if c.algo == "csac"), None)
        for base in (c for c in cells if c.algo in ("naive", "sac")):
            if ours is None:
                continue
            x, y = [m.final for m in found[ours]], [m.final for m in found[base]]
            lines.append(f"| {domain} | {label(ours)} | {label(base)} | "
                         f"{improvement(x, y)} |")
    return lines


def markdown(rows: list[dict], improvements: list[str]) -> str:
    fmt = lambda x: "–" if x is None else f"{x:.2f}"
    head = ("| maze | method | env steps | seeds | mean [95 % CI] | IQM [95 % CI] | per seed | solved (≥ 0.5) "
            "| running success ≥ 0.5 at (env steps, per seed) | paper (3 M, 5 seeds) |\n|---|---|---|---|---|---|---|---|---|---|\n")
    table = "".join(
        f"| {r['domain']} | {r['method']} | {r['env_steps']:,} | {r['seeds']} | {r['mean']} | {r['iqm']} | "
        f"{' '.join(f'{v:.2f}' for v in r['finals'])} | {r['solved']} of {r['seeds']} | "
        f"{' '.join('never' if s is None else f'{s / 1e6:.2f} M' for s in r['solved_at'])} | {fmt(r['paper'])} |\n"
        for r in rows)
    decay = "".join(f"| {r['domain']} | {r['method']} | {' '.join(f'{p:.2f}' for p in r['peak'])} | "
                    f"{' '.join(f'{round(d, 2) + 0.0:.2f}' for d in r['drop'])} |\n" for r in rows)
    ends = "".join(f"| {r['domain']} | {r['method']} | {r['ends']} |\n" for r in rows)
    return (f"# Table I's maze rows at the paper's budget\n\nSeeds {SEEDS[0]}–{SEEDS[-1]} (never used to choose a "
            "setting); [64, 64] networks (the paper's are [256, 256]), buffer 1e6, the paper's epoch (5000 env steps, "
            "1000 updates). Final success: mean of the last 10 evaluations (10 deterministic episodes each). "
            f"Intervals: 95 % stratified bootstrap over seeds. A cell below 3,000,000 env steps is still training; "
            f"one with fewer than {len(SEEDS)} seeds has its other seeds still to train (a cell may be trained in "
            "chunks of seeds).\n\n"
            + head + table
            + "\n## Does success decay after its peak?\n\nPer seed: the best 10-epoch running success, and its drop "
              "to the final success.\n\n| maze | method | peak per seed | drop per seed |\n|---|---|---|---|\n" + decay
            + "\n## Where the last evaluations end\n\nPer seed: the room (1 = first) the last 10 evaluations' episodes "
              "end in, mean, and the fraction ending in a dead-end pocket.\n\n| maze | method | seed: end |\n"
              "|---|---|---|\n" + ends
            + "\n## Probability of improvement\n\nP(a seed of CSAC at our ratio ends above a seed of the baseline; "
              "ties count half), 95 % bootstrap interval.\n\n| maze | CSAC | baseline | P(CSAC > baseline) |\n"
              "|---|---|---|---|\n" + "\n".join(improvements) + "\n")


def csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["domain", "method", "env_steps", "seeds", "mean_ci", "iqm_ci", "final_per_seed", "solved",
                     "first_success_per_seed", "solved_at_per_seed", "peak_per_seed", "paper"])
    for r in rows:
        writer.writerow([r["domain"], r["method"], r["env_steps"], r["seeds"], r["mean"], r["iqm"],
                         " ".join(f"{v:.3f}" for v in r["finals"]), r["solved"],
                         " ".join("never" if f is None else str(f) for f in r["first"]),
                         " ".join("never" if f is None else str(f) for f in r["solved_at"]),
                         " ".join(f"{p:.3f}" for p in r["peak"]), "" if r["paper"] is None else r["paper"]])
    return buf.getvalue()


def figure(domain: str, found: dict[Cell, list[Member]], path: Path) -> None:
    """The running success against env steps, each method's mean over seeds with its 95 % bootstrap band; the
    paper's final value at 3 M."""
    from matplotlib.ticker import FuncFormatter

    from ccp_jax import plot

    fig = plot.new_figure()
    ax = fig.axes[0] if fig.axes else fig.add_subplot()
    for i, (cell, members) in enumerate((c, m) for c, m in found.items() if c.domain == domain):
        points = min(m.running.size for m in members)
        if points == 0:
            continue
        steps = members[0].steps[WINDOW - 1:WINDOW - 1 + points]
        mean, low, high = stats.curve_band(np.stack([m.running[:points] for m in members]))
        color = f"C{i}"
        ax.plot(steps, mean, color=color, label=f"{label(cell)} ({len(members)} seeds)")
        ax.fill_between(steps, low, high, color=color, alpha=0.2, linewidth=0)
        if (paper := paper_value(cell)) is not None:
            ax.plot([3_000_000], [paper], marker="*", markersize=11, color=color, linestyle="none")
    ax.xaxis.set_major_formatter(FuncFormatter(plot._steps_label))
    ax.set(xlabel="env steps", ylabel=f"evaluation success, last {WINDOW} epochs", ylim=(-0.02, 1.02),
           title=f"{domain[-1]}-room maze at the paper's budget (★: the paper's Table I)")
    ax.legend(fontsize="small")
    plot.save_figure(fig, path)


def report(out: Path) -> str:
    found = {cell: members for cell in QUEUE if (members := load_cell(out, cell))}
    if not found:
        raise SystemExit(f"error: out: no runs of paper_budget.py in {out.resolve()}")
    rows = [cell_row(cell, members) for cell, members in found.items()]
    text = markdown(rows, improvement_lines(found))
    write_text(out / "table.md", text)
    write_text(out / "table.csv", csv_text(rows))
    for domain in dict.fromkeys(c.domain for c in found):
        figure(domain, found, out / f"curves_{domain}.png")
    print(text)
    return text


if __name__ == "__main__":
    report(Path(sys.argv[1]) if len(sys.argv) > 1 else RESULTS / "paper_budget")
