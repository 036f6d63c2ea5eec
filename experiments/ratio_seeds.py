"""Is the 3-room ratio chosen at the `cpu` scale (η = 0.3) better than the paper's (η = 0.1) on seeds no choice saw?

    python experiments/ratio_seeds.py        # -> experiments/results/ratio_seeds_maze3.md

Reads committed runs only, every one the 3-room maze with [64, 64] networks, and scores each member as Table I
does at the `cpu` scale: the mean evaluation success of its last 10 epochs up to 300 k env steps. Runs longer
than that (the paper-budget cells) are cut at 300 k. Below 2e5 transitions in every agent's buffer a run with a
1e6 buffer computes what one with 2e5 would (sampling reads only the filled part); the report says where a
buffer held more by 300 k.

Seed sets: 0-2 chose the ratio (Table I); 0-5 trained it again at 2e5 and showed that per-seed outcomes do not
survive a change of floating-point order (the same config at an older and at the current code); 30-34 (the
paper budget) and 40-45 (the sweeps of the population comparison) were never used for a choice, and the
verdict uses only those.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np

from common import RESULTS, cli, improvement, mean_and_iqm, rows_by_member, write_text

STEPS = 300_000
FRESH = "fresh"


@dataclasses.dataclass(frozen=True)
class Source:
    eta: float
    seeds: str  # what the seed set is
    folders: tuple[str, ...]  # under experiments/results
    kind: str = ""  # FRESH: seeds never used for a choice


SOURCES = (
    Source(0.1, "0–2, Table I (the choice)", ("table1_cpu_forward_slide/maze3/csac",)),
    Source(0.1, "0–5, an older build", ("kinematics_3room/csac_eta_0.1",)),
    Source(0.1, "0–5, the current build", ("kinematics_3room/csac_eta_0.1_rerun",)),
    Source(0.1, "30–34, paper budget (first 300 k)", ("paper_budget/maze3/csac_0.1",), FRESH),
    Source(0.1, "40–45, the population comparison's sweeps", tuple(f"pbt_compare_cpu/maze3/sweep_b{b}" for b in range(3)),
           FRESH),
    Source(0.3, "0–2, Table I (the choice)", ("table1_cpu_forward_slide/maze3/csac",)),
    Source(0.3, "30–34, paper budget (first 300 k)", ("paper_budget/maze3/csac_0.3",), FRESH),
    Source(0.3, "40–45, the population comparison's sweeps", tuple(f"pbt_compare_cpu/maze3/sweep_b{b}" for b in range(3)),
           FRESH),
)


@dataclasses.dataclass
class Args:
    root: Path = RESULTS
    """The results folder the sources are under."""


def scores(folder: Path, eta: float) -> Optional[tuple[dict[int, float], int]]:
    """{seed: final success at STEPS} of the members training at a shared `eta`, and the most transitions any of
    their agents' buffers held by then; None where the folder is not committed (yet)."""
    from ccp_jax import outputs

    if not (folder / "summary.json").exists():
        return None
    capacity = outputs.read_config(folder).sac.buffer_size
    finals: dict[int, float] = {}
    held = 0
    for rows in rows_by_member(folder).values():
        rows = [r for r in rows if r["env_steps"] <= STEPS]
        cooperative = rows[0]["eta"][:-1]  # the last agent's is 1
        if any(x == "auto" or not np.isclose(x, eta) for x in cooperative):
            continue
        finals[rows[0]["seed"]] = float(np.mean([r["success_rate"] for r in rows[-outputs.FINAL_WINDOW:]]))
        held = max(held, *(int(round(max(r.get("buffer_fill", [0.0])) * capacity)) for r in rows))
    return dict(sorted(finals.items())), held


def report(root: Path) -> str:
    lines = [f"### 3 rooms, η = 0.1 against 0.3: final success at {STEPS:,} env steps", "",
             "| η | seeds | per seed | solved (≥ 0.5) | mean [95 % CI] | IQM [95 % CI] | most transitions in a buffer |",
             "|---|---|---|---|---|---|---|"]
    fresh: dict[float, list[float]] = {}
    for src in SOURCES:
        found = [scores(root / f, src.eta) for f in src.folders]
        if any(f is None for f in found):
            lines.append(f"| {src.eta} | {src.seeds} | not committed yet | | | | |")
            continue
        values = {seed: v for per_seed, _ in found for seed, v in per_seed.items()}
        held = max(h for _, h in found)
        finals = list(values.values())
        if src.kind == FRESH:
            fresh.setdefault(src.eta, []).extend(finals)
        lines.append(f"| {src.eta} | {src.seeds} | {' '.join(f'{v:.2f}' for v in finals)} | "
                     f"{sum(v >= 0.5 for v in finals)} of {len(finals)} | {mean_and_iqm(finals)} | {held:,} |")
    if len(fresh) == 2:
        low, high = fresh[0.1], fresh[0.3]
        lines += ["", f"Seeds never used for a choice (30–34, 40–45): η = 0.1 {mean_and_iqm(low).replace(' | ', ', IQM ')} "
                      f"({sum(v >= 0.5 for v in low)} of {len(low)} solved); η = 0.3 "
                      f"{mean_and_iqm(high).replace(' | ', ', IQM ')} ({sum(v >= 0.5 for v in high)} of {len(high)}); "
                      f"P(η = 0.1 > η = 0.3) = {improvement(low, high)}."]
    return "\n".join(lines) + "\n"


def main(args: Args) -> None:
    text = report(args.root)
    write_text(args.root / "ratio_seeds_maze3.md", text)
    print(text)


if __name__ == "__main__":
    cli(main, Args)
