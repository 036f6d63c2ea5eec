"""Issue 59: does one PBT population find ratios as good as a sweep of the same cost?

    python experiments/pbt_compare.py --domains maze2 --blocks 3          # train what is missing, then report
    python experiments/pbt_compare.py --domains maze2 --blocks 3 --report-only

Per domain and per block of seeds, two grids of the same P members (the
starting ratios × `--seeds-per-block` seeds, at the scale's budget): a fixed
sweep (<domain>/sweep_b<k>/) and a population (<domain>/pbt_b<k>/, the
same grid with `--pbt-every`). Both cost the same env steps and updates.
The seeds start at 40 (`FIRST_SEED`): never used for any choice before.
With `--auto-rule RULE` (after every block's sweep and population), a third
grid of P members of `--eta auto --eta-auto-rule RULE` (<domain>/<rule>_b<k>/,
the best one-run rule of docs/results.md, `trusted`), on P seeds of its own
from `AUTO_FIRST_SEED`: the same cost again.

What the report (`pbt_compare.md` in the results folder) says, over the blocks:

* **best member**: the member a user of that one grid would keep, picked by
  the fitness of its training episodes over the last `pbt_every` epochs (the
  mean fraction of stages completed, PBT's own fitness, read from the rows);
  the same rule for both grids, and scored by its evaluation success (the
  paper's final success, over the epochs since its last copy if that was
  within them), which the pick never saw.
* **median member** of each grid.
* **the sweep's ratio on fresh seeds**: the ratio with the best mean final
  evaluation success in one block's sweep (a sweep's post-hoc pick), scored
  by that ratio's members in the other blocks' sweeps (seeds it was not
  picked on); one value per block.
* the population's final ratios per cooperative agent, and the wall time of
  each population against its sweep (same process pinned the same way,
  consecutive).

Intervals: 95 % stratified-bootstrap intervals over the blocks, mean and IQM;
P(population's best > sweep's best, and > the auto rule's) over all pairs of blocks.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np

from ccp_jax.eta import AUTO, ETA_AUTO_RULES
from common import (DOMAINS, SCALES, ScaleName, best_swept_eta, cli, eta_label, improvement, mean_and_iqm, read_json,
                    results_folder, rows_by_member, run_grid, write_text)

FIRST_SEED = 40  # seeds 40+: never used for a choice (Table I's sweeps use 0-11, the paper budget 30-34)
AUTO_FIRST_SEED = 100  # the auto rule's grids: P seeds per block from here


@dataclasses.dataclass
class Args:
    scale: ScaleName = "cpu"
    domains: tuple[str, ...] = ("maze2",)
    blocks: int = 3
    """Independent repetitions (blocks of seeds); each trains one sweep and one population."""
    etas: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)
    """Starting ratios (shared by every cooperative agent); the sweep trains exactly these."""
    seeds_per_block: int = 2
    """Seeds per starting ratio in a block: P = len(etas) × seeds_per_block members."""
    pbt_every: int = 2
    """The population's ranking interval in epochs (`--pbt-every`)."""
    out: Optional[Path] = None
    """Results folder (default experiments/results/pbt_compare_<scale>)."""
    auto_rule: Optional[str] = None
    """Also train P members of `--eta auto` with this rule per block (e.g. trusted), after the sweeps and
    populations."""
    report_only: bool = False
    """Write the report from the finished blocks; train nothing."""


def block_seed(args: Args, block: int) -> int:
    return FIRST_SEED + block * args.seeds_per_block


def grid_config(args: Args, domain: str, block: int, arm: str):
    """The grid of one arm ("sweep", "pbt" or the auto rule) in one block."""
    scale = SCALES[args.scale]
    if arm == args.auto_rule:
        size = len(args.etas) * args.seeds_per_block
        return scale.config(domain, "csac", ((AUTO,),), seeds=size, first_seed=AUTO_FIRST_SEED + block * size,
                            eta_auto_rule=arm)
    cooperative = DOMAINS[domain][1] - 1 if DOMAINS[domain][0] == "maze" else 1
    etas = tuple((e,) * cooperative for e in args.etas)
    changes = dict(pbt_every=args.pbt_every) if arm == "pbt" else {}
    return scale.config(domain, "csac", etas, seeds=args.seeds_per_block, first_seed=block_seed(args, block),
                        **changes)


def folder(out: Path, domain: str, block: int, arm: str) -> Path:
    return out / domain / f"{arm}_b{block}"


# ------------------------------------------------------------------ reading a finished grid
def training_fitness(rows: list[dict], window: int) -> float:
    """PBT's fitness (`ccp_jax.pbt.fitness`) from a member's last `window` rows: of the training episodes that
    ended, the mean fraction of the N stages completed. Entry n of a row's `train_stage_fraction` is the fraction
    of episodes that reached stage n (0-based), i.e. completed n stages; a success completed all N."""
    episodes = completed = 0.0
    for r in rows[-window:]:
        fractions, n = r["train_stage_fraction"], len(r["train_stage_fraction"])
        completed += r["train_episodes"] * (sum(fractions[1:]) + r["train_success"]) / n
        episodes += r["train_episodes"]
    return completed / episodes if episodes else 0.0


def carried_lines(rows: dict[int, list[dict]]) -> dict[int, int]:
    """{member: the starting member whose line it carries at the end}, following each copy (`pbt_parent`) in
    epoch order; every member its own line where the rows have no PBT fields (a sweep)."""
    line = {m: m for m in rows}
    for epoch in range(min(len(r) for r in rows.values())):
        parents = {m: r[epoch].get("pbt_parent", -1) for m, r in rows.items()}
        line = {m: line[p] if p >= 0 else line[m] for m, p in parents.items()}  # copies read the state before
    return line


def final_success(rows: list[dict]) -> float:
    """The paper's final success (the mean evaluation success of the last `FINAL_WINDOW` epochs) of a member's
    rows, counting only epochs since its last copy: a slot that copied a donor late is scored on the donor's
    line alone. (A copy follows the epoch's evaluation, so the epochs after it are the new line's.)"""
    from ccp_jax.outputs import FINAL_WINDOW

    copied = [i for i, r in enumerate(rows) if r.get("pbt_parent", -1) >= 0]
    since = rows[copied[-1] + 1:] if copied and copied[-1] + 1 < len(rows) else rows
    return float(np.mean([r["success_rate"] for r in since[-FINAL_WINDOW:]]))


def grid_scores(run: Path, window: int) -> dict:
    """A finished grid: per member (seed, the cooperative agents' starting and final ratios, fitness, final
    success), the member kept by fitness, the median success, the wall time, and the starting ratio a sweep's
    user would pick afterwards (`common.best_swept_eta`: the best mean final success, ties by return)."""
    summary = read_json(run / "summary.json")
    rows = rows_by_member(run)
    line = carried_lines(rows)
    members = [dict(seed=m["seed"], eta=m["eta"][:-1], final_eta=m.get("pbt_eta", m["eta"])[:-1],
                    fitness=training_fitness(rows[m["member"]], window), success=final_success(rows[m["member"]]),
                    line=line[m["member"]]) for m in summary["members"]]
    best = max(members, key=lambda m: m["fitness"])  # ties: the first member
    picked = best_swept_eta(summary)  # None for a grid of auto members
    return dict(members=members, best=best, median=float(np.median([m["success"] for m in members])),
                wall_s=summary.get("wall_s"), picked_eta=None if picked is None else picked[0])


def by_eta(grid: dict) -> dict[float, list[float]]:
    out: dict[float, list[float]] = {}
    for m in grid["members"]:
        out.setdefault(m["eta"][0], []).append(m["success"])
    return out


def sweep_pick_on_fresh_seeds(sweeps: list[dict]) -> list[tuple[float, float]]:
    """Per block: (the ratio picked there, `picked_eta`, and its mean success in the other blocks)."""
    picks = []
    for k, grid in enumerate(sweeps):
        pick = grid["picked_eta"]
        others = [s for j, g in enumerate(sweeps) if j != k for s in by_eta(g)[pick]]
        picks.append((pick, float(np.mean(others))))
    return picks


# ------------------------------------------------------------------ the report
def report(args: Args, out: Path, domain: str) -> Optional[str]:
    pairs = [(folder(out, domain, b, "sweep"), folder(out, domain, b, "pbt")) for b in range(args.blocks)]
    pairs = [(s, p) for s, p in pairs if (s / "summary.json").exists() and (p / "summary.json").exists()]
    if not pairs:
        return None
    sweeps = [grid_scores(s, args.pbt_every) for s, _ in pairs]
    pops = [grid_scores(p, args.pbt_every) for _, p in pairs]
    best_sweep, best_pop = [g["best"]["success"] for g in sweeps], [g["best"]["success"] for g in pops]
    fresh = sweep_pick_on_fresh_seeds(sweeps) if len(sweeps) > 1 else []
    lines = [f"### {domain}: {len(pairs)} blocks of {len(sweeps[0]['members'])} members, "
             f"{SCALES[args.scale].total_steps[domain]:,} env steps each", "",
             "| grid | kept member (by training fitness) | mean [95 % CI] | IQM [95 % CI] | per block |",
             "|---|---|---|---|---|"]
    for name, values in (("population", best_pop), ("sweep", best_sweep)):
        lines.append(f"| {name} | best | {mean_and_iqm(values)} | {' '.join(f'{v:.2f}' for v in values)} |")
    for name, grids in (("population", pops), ("sweep", sweeps)):
        values = [g["median"] for g in grids]
        lines.append(f"| {name} | median | {mean_and_iqm(values)} | {' '.join(f'{v:.2f}' for v in values)} |")
    autos = [grid_scores(f, args.pbt_every) for b in range(args.blocks)
             if ((f := folder(out, domain, b, args.auto_rule)) / "summary.json").exists()] if args.auto_rule else []
    if autos:
        for which, values in (("best", [g["best"]["success"] for g in autos]), ("median", [g["median"] for g in autos])):
            if values:
                blocks = f"{len(values)} block{'s' * (len(values) > 1)}"
                lines.append(f"| auto, {args.auto_rule} ({blocks}) | {which} | {mean_and_iqm(values)} | "
                             f"{' '.join(f'{v:.2f}' for v in values)} |")
    if fresh:
        values = [v for _, v in fresh]
        lines.append(f"| sweep's pick, on the other blocks' seeds | η = "
                     f"{', '.join(eta_label(e) for e, _ in fresh)} | {mean_and_iqm(values)} | "
                     f"{' '.join(f'{v:.2f}' for v in values)} |")
    lines += ["", f"P(population's kept member > sweep's kept member), over all pairs of blocks: "
                  f"{improvement(best_pop, best_sweep)}."]
    if autos:
        lines += [f"P(population's kept member > auto's kept member), over all pairs of blocks: "
                  f"{improvement(best_pop, [g['best']['success'] for g in autos])}."]
    lines += [""]
    lines += ["| block | seeds | population's kept member: final ratios | its success | the line it carries "
              "(start η, seed) | lines left at the end | all final ratios | wall s, population / sweep |",
              "|---|---|---|---|---|---|---|---|"]
    for k, (pop, sweep) in enumerate(zip(pops, sweeps)):
        b, start = pop["best"], {i: m for i, m in enumerate(pop["members"])}
        root = start[b["line"]]
        finals = " ".join("/".join(f"{e:.2f}" for e in m["final_eta"]) for m in pop["members"])
        wall = (f"{pop['wall_s']:.0f} / {sweep['wall_s']:.0f}" if pop["wall_s"] and sweep["wall_s"] else "–")
        lines.append(f"| {k} | {sorted({m['seed'] for m in pop['members']})} | "
                     f"{'/'.join(f'{e:.2f}' for e in b['final_eta'])} | {b['success']:.2f} | "
                     f"{'/'.join(eta_label(e) for e in root['eta'])}, {root['seed']} | "
                     f"{len({m['line'] for m in pop['members']})} | {finals} | {wall} |")
    return "\n".join(lines)


def main(args: Args) -> None:
    out = results_folder(args.out, "pbt_compare", args.scale, args.domains)
    if args.auto_rule is not None and args.auto_rule not in ETA_AUTO_RULES:
        raise SystemExit(f"error: auto_rule: unknown {args.auto_rule!r}; choose from {ETA_AUTO_RULES}")
    if not args.report_only:
        for domain in args.domains:
            arms = [(block, arm) for block in range(args.blocks) for arm in ("sweep", "pbt")]
            arms += [(block, args.auto_rule) for block in range(args.blocks) if args.auto_rule]
            for block, arm in arms:
                run_grid(grid_config(args, domain, block, arm), folder(out, domain, block, arm), checkpoint_every=5)
    sections = [s for d in args.domains if (s := report(args, out, d))]
    if sections:
        write_text(out / "pbt_compare.md", "\n\n".join(sections) + "\n")
        print("\n\n".join(sections))


if __name__ == "__main__":
    cli(main, Args, largest_grid=lambda a: len(a.etas) * a.seeds_per_block)
