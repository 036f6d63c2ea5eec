"""Table I of the paper: success of CSAC for each shared ratio η, of SAC and of Naive, per domain.

    python experiments/table1.py --scale cpu                    # reduced budget (see experiments/README.md)
    python experiments/table1.py --scale paper --domains maze3  # the paper's budget for one domain
    python experiments/table1.py --scale cpu --table-only       # rebuild the table from finished runs

Each (domain, algorithm) is one grid call, ratios × seeds vmapped, written to
OUT/<domain>/<algo>/ (config.json, metrics.jsonl, summary.json); a subset of the
CSAC ratios (`--etas`) to OUT/<domain>/csac_etas_<ratios>/, gathered into the
same table rows. Runs are done
domain by domain and the table is rewritten after each, so an interrupted
sweep leaves a partial table and resumes where it stopped. Success is the
paper's: mean evaluation success over the last 10 epochs, mean ± std over seeds.

TP (`--algo tp`) runs last in each domain, with one member of that domain's
Naive run as its frozen primitives: by default the member that got furthest
(`--tp-primitives-member best`), as a user would keep the primitives that work. The CSAC grid also holds `auto` members (η* from running critic ranges,
issue 9), trained with the same seeds as the swept ratios.
"""
from __future__ import annotations

import csv
import dataclasses
import io
from pathlib import Path
from typing import Literal, Optional

import numpy as np

from ccp_jax import stats
from ccp_jax.eta import AUTO, parse_eta
from common import (ALGO_NAMES, DOMAINS, PAPER_TABLE1, SCALES, ScaleName, cli, eta_label, final_ends, final_success, fmt,
                    improvement, mean_std, merged_summary, read_json, results_folder, run_grid, swept_folder, swept_runs,
                    with_interval, write_text)

ALGOS = ("csac", "sac", "naive", "tp")


@dataclasses.dataclass
class Args:
    scale: ScaleName = "cpu"
    """Budget: cpu (hours on a 2-core CPU), paper (3M steps, 5 seeds; needs a GPU), smoke (seconds)."""
    domains: tuple[str, ...] = ("maze2", "maze3", "maze4", "peg")
    """Any of maze2, maze3, maze4, peg, and pusher (Brax's, issue 11: not in the paper)."""
    algos: tuple[str, ...] = ("csac", "sac", "naive", "tp")
    """tp runs last: its primitives are the domain's Naive agents."""
    etas: Optional[tuple[str, ...]] = None
    """CSAC ratios to sweep instead of the scale's (numbers in [0, 1] or auto), e.g. --etas 0.9 auto. A subset is
    its own run (OUT/<domain>/csac_etas_<ratios>/); the table gathers every subset run with the full sweep, so a
    sweep can be completed piece by piece (--etas 0.1 0.3, later --etas 0.5 0.7)."""
    tp_primitives_member: int | Literal["best"] = "best"
    """Which Naive grid member (seed) provides TP's primitives; best: highest final success, then final return."""
    out: Optional[Path] = None
    """Results folder (default experiments/results/table1_<scale>)."""
    table_only: bool = False
    """Only rebuild table.md / table.csv from the runs already finished."""


def run_dir(out: Path, domain: str, algo: str) -> Path:
    return out / domain / algo


def best_member(summary: dict) -> int:
    """The grid member whose agents got furthest: highest final success, ties broken by final return."""
    return max(summary["members"], key=lambda m: (m["final_success"], m["final_return"]))["member"]


def covered_ratios(out: Path, domain: str, seeds: int) -> set:
    """The shared ratios (an eta vector's first entry) that finished CSAC runs of `domain` hold for seeds 0..seeds−1."""
    summary = merged_summary(swept_runs(out, domain))
    trained: dict = {}
    for m in summary["members"] if summary else []:
        trained.setdefault(m["eta"][0], set()).add(m["seed"])
    return {eta for eta, got in trained.items() if got >= set(range(seeds))}


def train_domain(scale_name: str, domain: str, algos: tuple[str, ...], out: Path,
                 primitives_member: int | Literal["best"] = "best", etas: Optional[tuple[str, ...]] = None) -> None:
    """Trains (or resumes, or skips) every algorithm's grid of one domain.

    CSAC sweeps `etas`, or else the scale's ratios less those that finished `--etas` runs of the domain
    already hold for every seed (all of them, into csac/, when there are none).

    TP's frozen primitives are member `primitives_member` (or the best member) of this domain's Naive run,
    trained first, so every TP seed reuses one set of primitives, as in the paper.
    """
    scale = SCALES[scale_name]
    sweep = tuple(parse_eta(e, "etas") for e in etas) if etas else tuple(scale.etas)
    if not etas and not (swept_folder(out, domain) / "config.json").exists():
        sweep = tuple(e for e in sweep if e not in covered_ratios(out, domain, scale.seeds))
    csac_dir = swept_folder(out, domain, None if sweep == tuple(scale.etas) else sweep)
    for algo in sorted(algos, key=lambda a: a == "tp"):
        if algo == "csac" and not sweep:
            continue  # every ratio already trained by --etas runs
        ratios = [(e,) for e in sweep] if algo == "csac" else [(1.0,)]
        extra = {}
        if algo == "tp":
            naive = run_dir(out, domain, "naive")
            if not (naive / "summary.json").exists():
                raise SystemExit(f"error: algos: tp needs the Naive run of {domain} as primitives; add naive")
            if not (naive / "checkpoints").exists():
                raise SystemExit(f"error: algos: tp needs the checkpoints of {naive} (its primitives); remove that "
                                 "folder and run again to retrain Naive, deterministically, with them kept")
            member = best_member(read_json(naive / "summary.json")) if primitives_member == "best" else primitives_member
            extra = dict(primitives=str(naive), primitives_member=member)
        folder = csac_dir if algo == "csac" else run_dir(out, domain, algo)
        run_grid(scale.config(domain, algo, etas=ratios, **extra), folder,
                 keep_checkpoints=algo == "naive" and "tp" in algos)


def finished_runs(out: Path, domain: str, algo: str) -> list[Path]:
    """The finished run folders of (domain, algo): for CSAC every shared-ratio sweep run (csac/, csac_etas_*/)."""
    folders = swept_runs(out, domain) if algo == "csac" else [run_dir(out, domain, algo)]
    return [f for f in folders if (f / "summary.json").exists()]


def collect(out: Path, domains: tuple[str, ...], algos: tuple[str, ...]) -> list[dict]:
    """One row per (algo, eta, domain) from the finished runs: seeds' final successes and first successes."""
    rows = []
    for domain in domains:
        for algo in algos:
            summary = merged_summary(finished_runs(out, domain, algo))
            if summary is None:
                continue
            firsts: dict[tuple, list] = {}
            ends: dict[tuple, list] = {}
            walls = {tuple(m["eta"]): m["wall_s"] for m in summary["members"]}
            runs = {run: final_ends(Path(run)) for run in {m["run"] for m in summary["members"]}}
            for m in summary["members"]:
                firsts.setdefault(tuple(m["eta"]), []).append(m["first_success_env_steps"])
                ends.setdefault(tuple(m["eta"]), []).append(runs[m["run"]][m["member"]])
            for eta, values in final_success(summary).items():
                key = eta[0] if algo == "csac" else None
                reached = [f for f in firsts[eta] if f is not None]
                stage, pocket = zip(*ends[eta])
                rows.append(dict(algo=algo, eta=key, domain=domain, success=values, stage=stage,
                                 pocket=None if None in pocket else pocket,
                                 first_success=reached, seeds_succeeded=len(reached),
                                 env_steps=summary["members"][0]["env_steps"], wall_s=walls[eta]))
    return rows


def paper_value(algo: str, eta, domain: str) -> Optional[float]:
    if algo == "csac":
        return PAPER_TABLE1["csac"].get(eta, {}).get(domain) if eta != AUTO else None
    return PAPER_TABLE1.get(algo, {}).get(domain)


def method_table(rows: list[dict], domains: tuple[str, ...], cell_text) -> list[str]:
    """Markdown lines in the paper's layout, a row per method (and ratio), a column per domain: cell_text(row, paper)."""
    methods = sorted({(r["algo"], r["eta"]) for r in rows},
                     key=lambda m: (["csac", "sac", "naive", "tp"].index(m[0]),
                                    2.0 if m[1] == AUTO else (m[1] or 0.0)))
    cell = {(r["algo"], r["eta"], r["domain"]): r for r in rows}
    lines = ["| method | η | " + " | ".join(domains) + " |", "|" + "---|" * (len(domains) + 2)]
    for algo, eta in methods:
        cells = [cell_text(cell.get((algo, eta, domain)), paper_value(algo, eta, domain)) for domain in domains]
        lines.append(f"| {ALGO_NAMES[algo]} | {eta_label(eta) if algo == 'csac' else ''} | " + " | ".join(cells) + " |")
    return lines


def interval_text(values: list[float]) -> str:
    """'IQM 0.98 [0.95, 1.00], mean 0.98 [0.95, 1.00]': each with its 95 % stratified-bootstrap interval."""
    return f"IQM {with_interval(values, stats.iqm)}, mean {with_interval(values, stats.mean)}"


def intervals(rows: list[dict], domains: tuple[str, ...]) -> str:
    """The success table again as IQM and mean with intervals, then P(the best CSAC ratio beats each baseline)."""
    table = method_table(rows, domains, lambda r, _: interval_text(r["success"]) if r else "")
    lines = []
    for domain in domains:
        csac = [r for r in rows if r["domain"] == domain and r["algo"] == "csac" and r["eta"] != AUTO]
        if not csac:
            continue
        best = max(csac, key=lambda r: np.mean(r["success"]))
        for base in (r for r in rows if r["domain"] == domain and r["algo"] in ("naive", "sac", "tp")):
            lines.append(f"| {domain} | CSAC η = {eta_label(best['eta'])} | {ALGO_NAMES[base['algo']]} | "
                         f"{improvement(best['success'], base['success'])} |")
    return ("\n## With intervals\n\nPer cell, the seeds' final success as IQM and mean, each with its 95 % "
            "stratified-bootstrap interval (`ccp_jax.stats`); with 3 seeds the IQM is the mean and an interval spans most of "
            "what 3 values allow.\n\n" + "\n".join(table)
            + "\n\nP(a seed of the best CSAC ratio ends above a seed of the baseline; ties count half), with its 95 % "
              "bootstrap interval. The best ratio is picked on these same seeds, so this favours CSAC.\n\n"
              "| domain | CSAC | baseline | P(CSAC > baseline) |\n|---|---|---|---|\n" + "\n".join(lines) + "\n")


def markdown(rows: list[dict], domains: tuple[str, ...], scale_name: str) -> str:
    """Table I ('ours (paper)' per cell), then where each method's evaluation episodes end."""
    success = method_table(rows, domains, lambda r, paper: f"{mean_std(r['success']) if r else 'not run'} ({fmt(paper)})")
    per_seed = lambda key: lambda r, _: " ".join(f"{v:.1f}" for v in r[key]) if r and r[key] is not None else ""
    stages = method_table(rows, domains, per_seed("stage"))
    budgets = {r["domain"]: r["env_steps"] for r in rows}
    seeds = max((len(r["success"]) for r in rows), default=0)
    note = (f"\nScale `{scale_name}`: {seeds} seeds; env steps per run "
            + ", ".join(f"{d} {budgets[d]:,}" for d in domains if d in budgets)
            + ". Cells: ours, mean ± std over seeds of the final success (last 10 epochs' evaluation); "
              "the paper's Table I in parentheses (5 seeds, 3M steps; '–': not reported).\n")
    where = ("\n## Where the evaluation episodes end\n\nPer seed, the stage (room) the evaluation episodes end in, "
             "1 = the first, mean over the last 10 evaluations; a success ends in the last stage, so a member at 0.00 "
             "with a high value got stuck late, one at 1.0 never left the first stage.\n\n")
    text = "\n".join(success) + "\n" + note + intervals(rows, domains) + where + "\n".join(stages) + "\n"
    if any(r["pocket"] is not None for r in rows):
        pocket_rows = [r for r in rows if r["pocket"] is not None]
        text += ("\nPer seed, the fraction of the last 10 evaluations' episodes that end inside a dead-end pocket "
                 "(the maze's trap; runs that logged it):\n\n"
                 + "\n".join(method_table(pocket_rows, domains, per_seed("pocket"))) + "\n")
    return text


def csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["algo", "eta", "domain", "seeds", "success_mean", "success_std", "success_per_seed",
                     "seeds_succeeded", "first_success_mean_env_steps", "paper", "env_steps", "wall_s",
                     "final_stage_per_seed", "final_pocket_per_seed"])
    for r in rows:
        first = f"{np.mean(r['first_success']):.0f}" if r["first_success"] else ""
        writer.writerow([r["algo"], "" if r["eta"] is None else eta_label(r["eta"]), r["domain"], len(r["success"]),
                         f"{np.mean(r['success']):.3f}", f"{np.std(r['success']):.3f}",
                         " ".join(f"{v:.2f}" for v in r["success"]), r["seeds_succeeded"], first,
                         fmt(paper_value(r["algo"], r["eta"], r["domain"])), r["env_steps"],
                         "" if r["wall_s"] is None else f"{r['wall_s']:.0f}", " ".join(f"{v:.2f}" for v in r["stage"]),
                         "" if r["pocket"] is None else " ".join(f"{v:.2f}" for v in r["pocket"])])
    return buf.getvalue()


def write_table(out: Path, domains: tuple[str, ...], algos: tuple[str, ...], scale_name: str) -> str:
    rows = collect(out, domains, algos)
    text = markdown(rows, tuple(d for d in domains if any(r["domain"] == d for r in rows)), scale_name)
    write_text(out / "table.md", text)
    write_text(out / "table.csv", csv_text(rows))
    return text


def largest_grid(args: Args) -> Optional[int]:
    """The largest grid this call may train (`common.cli` splits the CPU for it): the CSAC sweep, else a baseline's
    seeds; None when it trains nothing."""
    if args.table_only:
        return None
    scale = SCALES[args.scale]
    ratios = len(args.etas or scale.etas) if "csac" in args.algos else 1
    return ratios * scale.seeds


def main(args: Args) -> str:
    out = results_folder(args.out, "table1", args.scale, args.domains)
    every = tuple(DOMAINS)  # the table covers every domain trained in `out`, not only this call's
    if not args.table_only:
        for domain in args.domains:
            train_domain(args.scale, domain, args.algos, out, args.tp_primitives_member, args.etas)
            write_table(out, every, ALGOS, args.scale)
    text = write_table(out, every, ALGOS, args.scale)
    print(text)
    return text


if __name__ == "__main__":
    cli(main, Args, largest_grid=largest_grid)
