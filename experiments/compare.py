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
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np
import tyro
from scipy import stats

from ccp_jax import plot
from common import read_json, write_text


@dataclasses.dataclass
class Args:
    variants: tyro.conf.Positional[tuple[str, ...]]
    """LABEL=DIR[,DIR...] per variant; the first is the one every other row is tested against."""
    at: tuple[int, ...] = (100_000, 150_000, 200_000)
    """Env steps at which to report the mean evaluation success (the evaluation at that epoch, per seed)."""
    solved: float = 0.5
    """A seed counts as solved when its final success is at least this (half its final evaluations)."""
    out: Optional[Path] = None
    """Also write the table here (markdown)."""


@dataclasses.dataclass(frozen=True)
class Row:
    label: str
    finals: np.ndarray  # float64[seeds], in seed order
    at: np.ndarray  # float64[len(Args.at)]: mean over seeds; NaN where a seed had not reached that step
    firsts: list  # env steps of each seed's first evaluation success (None: never)


def parse_variant(text: str) -> tuple[str, list[Path]]:
    """'LABEL=DIR[,DIR...]' -> (label, folders); exits naming the field on a malformed or missing entry."""
    label, sep, dirs = text.partition("=")
    if not sep or not label or not dirs:
        raise SystemExit(f"error: variants: expected LABEL=DIR[,DIR...], got {text!r}")
    folders = [Path(d) for d in dirs.split(",")]
    for folder in folders:
        if not (folder / "summary.json").exists():
            raise SystemExit(f"error: variants: {folder} holds no finished run (summary.json)")
    return label, folders


def variant_rows(label: str, folders: list[Path], at: tuple[int, ...]) -> list[Row]:
    """One row per (algo, ratio) group of the pooled folders."""
    groups = plot.load_curves(folders)
    summaries = {}
    for folder in folders:
        for m in read_json(folder / "summary.json")["members"]:
            summaries.setdefault((m["algo"], tuple(m["eta"]), m["seed"]), m)  # first folder wins, as load_curves
    rows = []
    for group in sorted(groups, key=plot.group_order):
        members = sorted((m for k, m in summaries.items() if k[:2] == group[1:]), key=lambda m: m["seed"])
        name = label if len(groups) == 1 else f"{label}, {plot.group_label(group)}"
        means = []
        for step in at:
            values = [v[s == step] for s, v in groups[group]]
            means.append(np.mean([x[0] for x in values]) if all(len(x) for x in values) else np.nan)
        rows.append(Row(name, np.array([m["final_success"] for m in members]), np.array(means),
                        [m["first_success_env_steps"] for m in members]))
    return rows


def table(rows: list[Row], at: tuple[int, ...], solved: float) -> str:
    steps = " / ".join(f"{s // 1000} k" for s in at)
    lines = [f"| variant | seeds | mean success at {steps} | final (mean ± std) | solved (final ≥ {solved:g}) "
             f"| Mann–Whitney p vs first row |", "|---|---|---|---|---|---|"]
    for i, row in enumerate(rows):
        p = "" if i == 0 else f"{stats.mannwhitneyu(row.finals, rows[0].finals, alternative='two-sided').pvalue:.3f}"
        milestones = " / ".join("–" if np.isnan(v) else f"{v:.2f}" for v in row.at)
        lines.append(f"| {row.label} | {len(row.finals)} | {milestones} | {row.finals.mean():.2f} ± "
                     f"{row.finals.std():.2f} | {int((row.finals >= solved).sum())} of {len(row.finals)} | {p} |")
    lines.append("")
    lines.append("Final success per seed: " + "; ".join(
        f"{row.label}: {' '.join(f'{v:.2f}' for v in row.finals)}" for row in rows))
    return "\n".join(lines) + "\n"


def main(args: Args) -> str:
    rows = [row for text in args.variants for row in variant_rows(*parse_variant(text), args.at)]
    text = table(rows, args.at, args.solved)
    if args.out:
        write_text(args.out, text)
    print(text)
    return text


if __name__ == "__main__":
    main(tyro.cli(Args))
