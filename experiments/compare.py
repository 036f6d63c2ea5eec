"""Variants side by side: mean success at given env steps, final success per seed, and a rank test.

    python experiments/compare.py "paper's units=results/yardstick_2room_6seeds/paper_rule" \\
        "one temperature=results/yardstick_2room_6seeds/own_scale,results/yardstick_2room_6seeds/own_scale_seeds6to11" \\
        --at 100000 150000 200000

Each variant is LABEL=DIR[,DIR...]: the run folders whose members it pools
(seeds trained in separate calls; `plot.load_curves` refuses to pool folders
whose settings differ). A folder holding several ratios gives one row per ratio.
Every row is compared with the first by a two-sided Mann–Whitney U test on the
per-seed final success (the mean of a run's last evaluations, as summary.json
defines it): seeds are the unit of evidence, and the finals are far from
normal (most seeds end at 0 or 1).

With `--reference`, each row also gets the chance that a study of `--draw`
seeds of that variant shows a curve at least as good as a reference curve at
every --at step: the fraction of all `draw`-seed subsets of its seeds whose
mean success reaches the reference at each step. For the prototype's curve (docs/design.md#the-learning-yardstick)
(3 seeds, 0.03 / 0.33 / 0.77 at 100 / 150 / 200 k) it says whether a curve
like the prototype's is a plausible draw of the variant, or a different
method.

A folder without summary.json is a run still training: its rows use the
evaluations logged so far (final = the mean of its last ones), and a line under
the table says how far it got, so a long grid can be watched as it trains.
"""
from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from typing import Optional

import numpy as np
import tyro
from scipy import stats

from ccp_jax import outputs, plot
from common import cli, mean_std, merged_summary, success_at, write_text


@dataclasses.dataclass
class Args:
    variants: tyro.conf.Positional[tuple[str, ...]]
    """LABEL=DIR[,DIR...] per variant; the first is the one every other row is tested against."""
    at: tuple[int, ...] = (100_000, 150_000, 200_000)
    """Env steps at which to report the mean evaluation success (the evaluation at that epoch, per seed)."""
    solved: float = 0.5
    """A seed counts as solved when its final success is at least this (half its final evaluations)."""
    reference: tuple[float, ...] = ()
    """A reference curve, the mean success at each --at step (e.g. the prototype's: 0.03 0.33 0.77)."""
    draw: int = 3
    """Seeds in the reference's study: the size of the seed subsets compared with --reference."""
    out: Optional[Path] = None
    """Also write the table here (markdown)."""

    def __post_init__(self):
        if self.reference and len(self.reference) != len(self.at):
            raise SystemExit(f"error: reference: one value per --at step ({len(self.at)}), got {len(self.reference)}")
        if self.draw < 1:
            raise SystemExit(f"error: draw: at least one seed, got {self.draw}")


@dataclasses.dataclass(frozen=True)
class Row:
    label: str
    finals: np.ndarray  # float64[seeds], in seed order
    per_seed_at: np.ndarray  # float64[seeds, len(Args.at)]: each seed's evaluation there; NaN where not reached

    @property
    def at(self) -> np.ndarray:
        """float64[len(Args.at)]: mean over seeds; NaN where a seed had not reached that step."""
        return self.per_seed_at.mean(0)

    def chance(self, reference: tuple[float, ...], draw: int) -> Optional[float]:
        """The fraction of `draw`-seed subsets whose mean success is at least `reference` at every step
        (None if the row has fewer seeds, or a seed has not reached a step yet)."""
        values = self.per_seed_at
        if len(values) < draw or np.isnan(values).any():
            return None
        hits = [np.all(values[list(subset)].mean(0) >= np.asarray(reference) - 1e-9)
                for subset in itertools.combinations(range(len(values)), draw)]
        return float(np.mean(hits))


def parse_variant(text: str) -> tuple[str, list[Path]]:
    """'LABEL=DIR[,DIR...]' -> (label, folders); exits naming the field on a malformed or missing entry."""
    label, sep, dirs = text.partition("=")
    if not sep or not label or not dirs:
        raise SystemExit(f"error: variants: expected LABEL=DIR[,DIR...], got {text!r}")
    folders = [Path(d) for d in dirs.split(",")]
    for folder in folders:
        if not ((folder / "config.json").exists() and outputs.metrics_file(folder).exists()):
            raise SystemExit(f"error: variants: {folder} holds no run (config.json and metrics.jsonl)")
    return label, folders


def progress(members: list[dict]) -> list[str]:
    """'DIR: 60,000 of 200,000 env steps' for each run folder of `members` still training (no summary.json)."""
    done: dict[str, int] = {}
    for m in members:
        if not (Path(m["run"]) / "summary.json").exists():
            done[m["run"]] = max(done.get(m["run"], 0), m["env_steps"])
    return [f"{run}: {steps:,} of {outputs.read_config(run).budget.total_steps:,} env steps"
            for run, steps in done.items()]


def variant_rows(label: str, folders: list[Path], at: tuple[int, ...]) -> tuple[list[Row], list[str]]:
    """One row per (algo, ratio) group of the pooled folders, and `progress` of those still training."""
    groups = plot.load_curves(folders)
    members = merged_summary(folders, in_progress=True)["members"]
    rows = []
    for group in sorted(groups, key=plot.group_order):
        finals = [m["final_success"] for m in sorted(members, key=lambda m: m["seed"]) if tuple(m["eta"]) == group[2]]
        per_seed = [[(success_at([one], step) or [np.nan])[0] for step in at] for one in groups[group]]
        rows.append(Row(plot.variant_label(label, group, groups), np.array(finals),
                        np.array(per_seed, np.float64).reshape(-1, len(at))))
    return rows, progress(members)


def table(rows: list[Row], at: tuple[int, ...], solved: float, reference: tuple[float, ...] = (), draw: int = 3) -> str:
    steps = " / ".join(f"{s // 1000} k" for s in at)
    head = (f"| variant | seeds | mean success at {steps} | final (mean ± std) | solved (final ≥ {solved:g}) "
            f"| Mann–Whitney p vs first row |")
    if reference:
        head += f" {draw} seeds reach {' / '.join(f'{v:g}' for v in reference)} |"
    lines = [head, "|---" * head.count("|", 1) + "|"]
    for i, row in enumerate(rows):
        p = "" if i == 0 else f"{stats.mannwhitneyu(row.finals, rows[0].finals, alternative='two-sided').pvalue:.3f}"
        milestones = " / ".join("–" if np.isnan(v) else f"{v:.2f}" for v in row.at)
        line = (f"| {row.label} | {len(row.finals)} | {milestones} | {mean_std(list(row.finals))} "
                f"| {int((row.finals >= solved).sum())} of {len(row.finals)} | {p} |")
        if reference:
            chance = row.chance(reference, draw)
            line += " – |" if chance is None else f" {chance:.3f} |"
        lines.append(line)
    lines.append("")
    lines.append("Final success per seed: " + "; ".join(
        f"{row.label}: {' '.join(f'{v:.2f}' for v in row.finals)}" for row in rows))
    return "\n".join(lines) + "\n"


def main(args: Args) -> str:
    rows, running = [], []
    for label, folders in [parse_variant(text) for text in args.variants]:  # every entry checked first
        variant, still = variant_rows(label, folders, args.at)
        rows += variant
        running += still
    text = table(rows, args.at, args.solved, args.reference, args.draw)
    if running:
        text += "\nStill training (finals so far: the mean of the last evaluations logged): " + "; ".join(running) + "\n"
    if args.out:
        write_text(args.out, text)
    print(text)
    return text


if __name__ == "__main__":
    cli(main, Args, errors=(ValueError,))  # a folder pair that must not pool, too
