"""Is the ratio chosen at the `cpu` scale better than the paper's, on seeds no choice saw?

    python experiments/ratio_seeds.py        # -> experiments/results/ratio_seeds_maze3.md and ratio_seeds_maze4.md

3 rooms: our η = 0.3 against the paper's 0.1. 4 rooms: our η = 0.5 and the per-agent ramp (0.1, 0.3, 0.5)
against the paper's 0.9, with η = 0.1 beside them (what the ramp's first agent uses). Reads committed runs only,
every one with [64, 64] networks, and scores each member as Table I does at the `cpu` scale: the mean evaluation
success of its last 10 epochs up to that scale's budget (300 k env steps on 3 rooms, 400 k on 4). Runs longer
than that (the paper-budget cells) are cut there. Below 2e5 transitions in every agent's buffer a run with a 1e6
buffer computes what one with 2e5 would (sampling reads only the filled part); the report says where a buffer held
more by the cut.

Seed sets: 0-2 chose the ratio (Table I); on 3 rooms 0-5 trained it again at 2e5 and showed that per-seed
outcomes do not survive a change of floating-point order; on 4 rooms 3-11 compared the ramp with η = 0.5 (a
choice too). 30-34 (the paper budget, whose cells may be split into grids `<cell>_seeds<a>to<b>`) and 40-45 (the
sweeps of the population comparison) were never used for a choice, and the verdict uses only those.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np

import paper_budget
import pbt_compare
from common import RESULTS, cli, improvement, mean_and_iqm, rows_by_member, write_text

FRESH = "fresh"
RAMP = (0.1, 0.3, 0.5)
BUDGET_SEEDS = paper_budget.SEEDS
SWEEP_BLOCKS = 3  # the 3- and 4-room population comparisons' blocks
SWEEP_SEEDS = tuple(range(pbt_compare.block_seed(pbt_compare.Args(), 0),
                          pbt_compare.block_seed(pbt_compare.Args(), SWEEP_BLOCKS)))


@dataclasses.dataclass(frozen=True)
class Source:
    eta: float | tuple[float, ...]  # shared by every cooperative agent, or one per cooperative agent
    seeds: str  # what the seed set is
    folders: tuple[str, ...]  # under experiments/results; a paper-budget cell also reads its `_seeds` chunks;
    # the committed ones are read, the rest reported as missing through `planned`
    kind: str = ""  # FRESH: seeds never used for a choice
    planned: tuple[int, ...] = ()  # the seeds the source will hold once every grid is committed


@dataclasses.dataclass(frozen=True)
class Domain:
    rooms: int
    steps: int  # the `cpu` scale's budget, where Table I's values are read
    ours: tuple[float | tuple[float, ...], ...]
    paper: float
    sources: tuple[Source, ...]


def _sweeps(rooms: int) -> tuple[str, ...]:
    out = Path("pbt_compare_cpu")
    return tuple(str(pbt_compare.folder(out, f"maze{rooms}", b, "sweep")) for b in range(SWEEP_BLOCKS))


T1 = "table1_cpu_forward_slide"
BOTH_3_11 = (f"{T1}/maze4/csac_ramp_and_0.5_seeds6to8", f"{T1}/maze4/csac_trusted_0.5_ramp_seeds9to11")  # 0.5 and ramp
DOMAINS = {
    3: Domain(3, 300_000, (0.3,), 0.1, (
        Source(0.1, "0–2, Table I (the choice)", (f"{T1}/maze3/csac",)),
        Source(0.1, "0–5, an older build", ("kinematics_3room/csac_eta_0.1",)),
        Source(0.1, "0–5, the current build", ("kinematics_3room/csac_eta_0.1_rerun",)),
        Source(0.1, "30–34, paper budget (first 300 k)", ("paper_budget/maze3/csac_0.1",), FRESH, BUDGET_SEEDS),
        Source(0.1, "40–45, the population comparison's sweeps", _sweeps(3), FRESH, SWEEP_SEEDS),
        Source(0.3, "0–2, Table I (the choice)", (f"{T1}/maze3/csac",)),
        Source(0.3, "30–34, paper budget (first 300 k)", ("paper_budget/maze3/csac_0.3",), FRESH, BUDGET_SEEDS),
        Source(0.3, "40–45, the population comparison's sweeps", _sweeps(3), FRESH, SWEEP_SEEDS),
    )),
    4: Domain(4, 400_000, (0.5, RAMP), 0.9, (
        Source(0.1, "0–2, Table I", (f"{T1}/maze4/csac_etas_0.1-0.3",)),
        Source(0.1, "30–34, paper budget (first 400 k)", ("paper_budget/maze4/csac_0.1",), FRESH, BUDGET_SEEDS),
        Source(0.1, "40–45, the population comparison's sweeps", _sweeps(4), FRESH, SWEEP_SEEDS),
        Source(0.9, "0–2, Table I", (f"{T1}/maze4/csac_etas_0.9-auto",)),
        Source(0.9, "30–34, paper budget (first 400 k)", ("paper_budget/maze4/csac_0.9",), FRESH, BUDGET_SEEDS),
        Source(0.9, "40–45, the population comparison's sweeps", _sweeps(4), FRESH, SWEEP_SEEDS),
        Source(0.5, "0–2, Table I (the choice)", (f"{T1}/maze4/csac_etas_0.5-0.7",)),
        Source(0.5, "3–11, the ramp's comparison", (f"{T1}/maze4/csac_fresh_seeds", *BOTH_3_11)),
        Source(0.5, "30–34, paper budget (first 400 k)", ("paper_budget/maze4/csac_0.5",), FRESH, BUDGET_SEEDS),
        Source(0.5, "40–45, the population comparison's sweeps", _sweeps(4), FRESH, SWEEP_SEEDS),
        Source(RAMP, "0–2, after Table I", (f"{T1}/maze4/csac_ramp",)),
        Source(RAMP, "3–11, the ramp's comparison", (f"{T1}/maze4/csac_ramp_fresh_seeds", *BOTH_3_11)),
        Source(RAMP, "30–34, paper budget (first 400 k)", ("paper_budget/maze4/csac_ramp",), FRESH, BUDGET_SEEDS),
    )),
}


@dataclasses.dataclass
class Args:
    root: Path = RESULTS
    """The results folder the sources are under."""


def label(eta: float | tuple[float, ...]) -> str:
    return f"{eta:g}" if isinstance(eta, float) else "(" + ", ".join(f"{e:g}" for e in eta) + ")"


def folders(root: Path, name: str) -> list[Path]:
    """The committed grids of one source folder: itself, or where a paper-budget cell was split by seeds, its
    `<name>_seeds<a>to<b>` chunks (`experiments/paper_budget.py`); none where nothing is committed (yet)."""
    whole = root / name
    if (whole / "summary.json").exists():
        return [whole]
    return [p for p in paper_budget.cell_grids(whole.parent, whole.name) if (p / "summary.json").exists()]


def scores(folder: Path, eta: float | tuple[float, ...], steps: int) -> Optional[tuple[dict[int, float], int]]:
    """{seed: final success at `steps`} of the members training at `eta` (a ratio every cooperative agent shares,
    or one per cooperative agent), and the most transitions any of their agents' buffers held by then; None where
    the folder is not committed (yet)."""
    from ccp_jax import outputs

    if not (folder / "summary.json").exists():
        return None
    capacity = outputs.read_config(folder).sac.buffer_size
    finals: dict[int, float] = {}
    held = 0
    for rows in rows_by_member(folder).values():
        rows = [r for r in rows if r["env_steps"] <= steps]
        cooperative = rows[0]["eta"][:-1]  # the last agent's is 1
        if "auto" in cooperative or not np.allclose(cooperative, np.broadcast_to(eta, len(cooperative))):
            continue
        finals[rows[0]["seed"]] = float(np.mean([r["success_rate"] for r in rows[-outputs.FINAL_WINDOW:]]))
        held = max(held, *(int(round(max(r.get("buffer_fill", [0.0])) * capacity)) for r in rows))
    return dict(sorted(finals.items())), held


def report(root: Path, domain: Domain) -> str:
    names = " and ".join(label(e) for e in domain.ours)
    lines = [f"### {domain.rooms} rooms, η = {names} against the paper's {label(domain.paper)}: "
             f"final success at {domain.steps:,} env steps", "",
             "| η | seeds | per seed | solved (≥ 0.5) | mean [95 % CI] | IQM [95 % CI] "
             "| most transitions in a buffer |",
             "|---|---|---|---|---|---|---|"]
    fresh: dict[str, list[float]] = {}
    for src in domain.sources:
        grids = [[scores(g, src.eta, domain.steps) for g in folders(root, f)] for f in src.folders]
        if not any(grids):
            lines.append(f"| {label(src.eta)} | {src.seeds} | not committed yet | | | | |")
            continue
        found = [s for per_folder in grids for s in per_folder]
        values = {seed: v for per_seed, _ in found for seed, v in per_seed.items()}
        finals = list(values.values())
        if src.kind == FRESH:
            fresh.setdefault(label(src.eta), []).extend(finals)
        seeds = src.seeds
        if src.planned and tuple(values) != src.planned:
            seeds += f" (so far {' '.join(str(s) for s in values)})"
        lines.append(f"| {label(src.eta)} | {seeds} | {' '.join(f'{v:.2f}' for v in finals)} | "
                     f"{sum(v >= 0.5 for v in finals)} of {len(finals)} | {mean_and_iqm(finals)} | "
                     f"{max(h for _, h in found):,} |")
    paper = fresh.get(label(domain.paper))
    lines.append("")
    for ours in (label(e) for e in domain.ours):
        if paper and fresh.get(ours):
            mine = fresh[ours]
            lines.append(f"Seeds never used for a choice: η = {ours} {mean_and_iqm(mine).replace(' | ', ', IQM ')} "
                         f"({sum(v >= 0.5 for v in mine)} of {len(mine)} solved); "
                         f"the paper's η = {label(domain.paper)} {mean_and_iqm(paper).replace(' | ', ', IQM ')} "
                         f"({sum(v >= 0.5 for v in paper)} of {len(paper)}); "
                         f"P(η = {ours} > η = {label(domain.paper)}) = {improvement(mine, paper)}.")
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def main(args: Args) -> None:
    for rooms, domain in DOMAINS.items():
        text = report(args.root, domain)
        write_text(args.root / f"ratio_seeds_maze{rooms}.md", text)
        print(text)


if __name__ == "__main__":
    cli(main, Args)
