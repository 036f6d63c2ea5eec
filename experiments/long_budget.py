"""The maze at several times the `cpu` scale's budget: do CSAC's traps let go given more steps?

    python experiments/long_budget.py                 # 2 rooms: trains (or resumes) the grids, then table and figure
    python experiments/long_budget.py --rooms 3       # 3 rooms
    python experiments/long_budget.py --rooms 3 --runs csac_own_scale --first-seed 3   # its seeds 3-5 too
    python experiments/long_budget.py --rooms 3 --runs csac_own_floor --first-seed 3 --seeds 6   # seeds 3-8
    python experiments/long_budget.py --rooms 3 --runs naive sac --first-seed 3   # the baselines' seeds 3-5 too
    python experiments/long_budget.py --rooms 3 --runs csac_own_scale --first-seed 9 --keep-checkpoints   # for ccp_jax.evaluate
    python experiments/long_budget.py --plot-only     # table and figure from the runs as they stand

SPEC §7's yardstick settings (the `cpu` scale: [64, 64] nets, the paper's epoch,
buffers of 2e5). 2 rooms (`long_2room/`): seeds 0–5, 750 k env steps (a quarter
of the paper's 3 M, 5x the `cpu` scale's 150 k): CSAC with η = 0.1 (the paper's
best 2-room ratio and SPEC §7's) and `auto`, both with the paper's batch
normaliser (one grid, csac_batch/), `auto` with the floor normaliser
(csac_auto_floor/), and η = 0.5, the `cpu` sweep's best ratio (csac_eta_0.5/).
3 rooms (`long_3room/`): seeds 0–2, 600 k (2x the `cpu` scale's 300 k): η = 0.1
(the paper's best), η = 0.3 (the `cpu` sweep's best) and `auto`, one grid
(csac_batch/), then η = 0.3 and `auto` with one temperature for actor and critic
(`--coop-scale own`, the best 2-room variant; csac_own_scale/), η = 0.3 with one
temperature and the floor normaliser at 5 (csac_own_floor/), and the paper's baselines
Naive (naive/) and end-to-end SAC (sac/). Writes into the
results folder: table.md (mean success at the milestones, for 2 rooms beside
SPEC §7's prototype, then per seed the final success, the first success and
where the last evaluations end) and success.png. `--first-seed K` trains seeds K.. of the
same runs into folders of their own (`<run>_seeds<K>to<K+seeds-1>/`); the table and figure
pool every seed folder of a run.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal, Optional

import numpy as np

from ccp_jax import outputs, plot
from ccp_jax.eta import AUTO
from common import (ALGO_NAMES, RESULTS, SCALES, ScaleName, cli, final_ends, fmt, mean_std, read_json, run_grid, success_at,
                    write_text)


@dataclasses.dataclass(frozen=True)
class Plan:
    """One maze's long runs: run folder -> (ratio grid, config changes), each on seeds 0..seeds-1."""

    runs: dict[str, tuple[tuple, dict]]
    seeds: int
    total_steps: int
    milestones: tuple[int, ...]


# η = 0.1 is the paper's best ratio on 2 and 3 rooms; 0.5 and 0.3 the `cpu` scale's best swept ones (Table I at
# 150 k and 300 k).
PLANS = {
    2: Plan(runs={"csac_batch": (((0.1,), (AUTO,)), {}),
                  "csac_auto_floor": (((AUTO,),), {"normaliser": "floor"}),
                  "csac_eta_0.5": (((0.5,),), {})},
            seeds=6, total_steps=750_000,
            milestones=(50_000, 100_000, 150_000, 200_000, 250_000, 300_000, 400_000, 515_000, 600_000, 750_000)),
    3: Plan(runs={"csac_batch": (((0.1,), (0.3,), (AUTO,)), {}),
                  "csac_own_scale": (((0.3,), (AUTO,)), {"coop_scale": "own"}),
                  # Seeds 4, 6 and 7 of η = 0.3 with one temperature stall in room 1 with a next critic whose batch
                  # range is ≈ 1–3 against its own 10–18: a floor of 5 (a quarter of the value bound 1 / (1 − γ))
                  # caps the weight that flat critic gets.
                  "csac_own_floor": (((0.3,),), {"coop_scale": "own", "normaliser": "floor", "norm_floor": 5.0}),
                  # The paper's baselines at the same budget: does CSAC's lead over them (Table I: 0.62 against
                  # Naive's 0.20 and SAC's 0.00) show once the best CSAC variant learns?
                  "naive": (((1.0,),), {"algo": "naive"}),
                  "sac": (((1.0,),), {"algo": "sac"})},
            seeds=3, total_steps=600_000,
            milestones=(100_000, 200_000, 300_000, 400_000, 500_000, 600_000)),
}
# SPEC §7: the prototype's mean success (CSAC η = 0.1, 3 seeds) at these env steps; 0.93–1.00 from 250 k to 515 k.
PROTOTYPE = {100_000: 0.03, 150_000: 0.33, 200_000: 0.77}
PROTOTYPE_PLATEAU = (250_000, 515_000, 0.93, 1.00)


@dataclasses.dataclass
class Args:
    rooms: Literal[2, 3] = 2
    scale: ScaleName = "cpu"
    seeds: Optional[int] = None
    """Seeds per run, from first_seed on; default the plan's (2 rooms: 6, 3 rooms: 3)."""
    first_seed: int = 0
    """Above 0: more seeds of the same runs, each into <run>_seeds<first>to<last>/ beside the plan's."""
    total_steps: Optional[int] = None
    """Default the plan's (2 rooms: 750 k, 3 rooms: 600 k)."""
    milestones: Optional[tuple[int, ...]] = None
    """Env steps at which the table gives the mean success over seeds (single evaluations); default the plan's."""
    runs: Optional[tuple[str, ...]] = None
    """Train only these of the plan's run folders (default all); the table and figure show every one found."""
    out: Optional[Path] = None
    """Default experiments/results/long_<rooms>room."""
    plot_only: bool = False
    """Never train: table and figure from whatever the folders hold (unfinished runs too)."""
    keep_checkpoints: bool = False
    """Keep each run's checkpoints once it finishes (for `python -m ccp_jax.evaluate`); deleted by default."""

    @property
    def plan(self) -> Plan:
        return PLANS[self.rooms]

    @property
    def folder(self) -> Path:
        return self.out or RESULTS / f"long_{self.rooms}room"

    def run_folder(self, run: str, seeds: int) -> Path:
        """Where `run` trains its seeds: the plan's folder, or a seed-range folder beside it."""
        if not self.first_seed:
            return self.folder / run
        return self.folder / f"{run}_seeds{self.first_seed}to{self.first_seed + seeds - 1}"


def seed_folders(out: Path, run: str) -> list[Path]:
    """`run`'s folder and its `--first-seed` folders (`<run>_seeds<a>to<b>`), lowest seed first."""
    first_seed = lambda p: int(p.name.removeprefix(f"{run}_seeds").split("to")[0])
    extra = sorted(out.glob(f"{run}_seeds*to*"), key=first_seed)
    return [out / run] + extra


def variant(eta: tuple, changes: dict) -> str:
    """A row's name: "CSAC η = 0.1", "auto, floor normaliser", "CSAC η = 0.3, one temperature", "Naive"."""
    if (algo := changes.get("algo", "csac")) != "csac":
        return ALGO_NAMES[algo]
    normaliser = changes.get("normaliser", "batch")
    name = "auto" if AUTO in eta else f"CSAC η = {eta[0]:g}"
    if AUTO in eta or normaliser != "batch":
        name += f", {normaliser} normaliser" + (f" {changes['norm_floor']:g}" if "norm_floor" in changes else "")
    return name + (", one temperature" if changes.get("coop_scale") == "own" else "")


def prototype(steps: int) -> str:
    if steps in PROTOTYPE:
        return f"{PROTOTYPE[steps]:.2f}"
    start, end, low, high = PROTOTYPE_PLATEAU
    return f"{low:.2f}–{high:.2f}" if start <= steps <= end else "–"


def load(out: Path, runs: dict[str, tuple[tuple, dict]]) -> dict[str, dict]:
    """{variant: {"curves": [(steps, success)] per member, "members": finished members' summaries, "ends": ...}}."""
    found = {}
    for folder, (_, changes) in runs.items():
        folders = [run for run in seed_folders(out, folder) if outputs.metrics_file(run).exists()]
        # load_curves pools the seed folders, refusing (or counting once) a seed found in two of them.
        for (_, _, eta), series in (plot.load_curves(folders) if folders else {}).items():
            found[variant(eta, changes)] = dict(curves=series, members=[], ends=[])
        seen = set()
        for run in folders:  # the per-seed table lists finished folders only: one still training adds no rows
            if not (run / "summary.json").exists():
                continue
            ends = final_ends(run)
            for m in read_json(run / "summary.json")["members"]:
                if (key := (tuple(m["eta"]), m["seed"])) not in seen:
                    seen.add(key)
                    entry = found[variant(key[0], changes)]
                    entry["members"].append(m)
                    entry["ends"].append(ends[m["member"]])
    # numeric ratios first, then auto, then the baselines (whose rows are named after their algorithm)
    baseline = lambda name: name in ALGO_NAMES.values()
    return dict(sorted(found.items(), key=lambda item: (baseline(item[0]), item[0].startswith("auto"))))


def milestone_table(found: dict[str, dict], milestones: tuple[int, ...], with_prototype: bool) -> list[str]:
    """Mean success over seeds at each milestone; with SPEC §7's prototype column (a 2-room yardstick)."""
    head = ["env steps"] + ["SPEC §7 prototype (η = 0.1, 3 seeds)"] * with_prototype + list(found)
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for steps in milestones:
        cells = [f"{steps:,}"] + [prototype(steps)] * with_prototype
        for v in found.values():
            at = success_at(v["curves"], steps)
            cells.append(f"{np.mean(at):.2f} ({len(at)})" if at else "–")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def seed_table(found: dict[str, dict]) -> list[str]:
    lines = ["| variant | final success | per seed | first success (env steps) | room the last evaluations end "
             "in, mean (fraction in a pocket) |", "|---|---|---|---|---|"]
    for name, v in found.items():
        if not v["members"]:
            continue
        finals = [m["final_success"] for m in v["members"]]
        firsts = " ".join("never" if m["first_success_env_steps"] is None else f"{m['first_success_env_steps']:,}"
                          for m in v["members"])
        ends = " ".join(f"{stage:.2f} ({fmt(pocket)})" for stage, pocket in v["ends"])
        lines.append(f"| {name} | {mean_std(finals)} | {' '.join(f'{x:.2f}' for x in finals)} | {firsts} | {ends} |")
    return lines


def figure(found: dict[str, dict], rooms: int, path: Path) -> None:
    groups = {(f"maze-{rooms}", name, ()): v["curves"] for name, v in found.items()}
    ax = plot.curves(groups, title=f"{rooms}-room maze, [64, 64]").axes[0]
    if rooms == 2:
        ax.plot(list(PROTOTYPE), list(PROTOTYPE.values()), "ko--", label="SPEC §7 prototype, η = 0.1 (3 seeds)")
        start, end, low, high = PROTOTYPE_PLATEAU
        ax.fill_between([start, end], low, high, color="k", alpha=0.25, linewidth=0)
        ax.legend(fontsize="small")
    ax.figure.savefig(path)


def largest_grid(args: Args) -> Optional[int]:
    """The largest grid this call may train (`common.cli` splits the CPU for it); None when it trains nothing."""
    if args.plot_only:
        return None
    seeds = args.plan.seeds if args.seeds is None else args.seeds
    return max((len(etas) * seeds for folder, (etas, _) in args.plan.runs.items()
                if not args.runs or folder in args.runs), default=None)


def main(args: Args) -> str:
    scale, plan, out = SCALES[args.scale], args.plan, args.folder
    if args.runs and (unknown := set(args.runs) - set(plan.runs)):
        raise SystemExit(f"error: runs: unknown {sorted(unknown)}; the {args.rooms}-room plan has {list(plan.runs)}")
    if not args.plot_only:
        seeds = plan.seeds if args.seeds is None else args.seeds
        total_steps = plan.total_steps if args.total_steps is None else args.total_steps
        for folder, (etas, changes) in plan.runs.items():
            if args.runs and folder not in args.runs:
                continue
            changes = dict(changes)
            run_grid(scale.config(f"maze{args.rooms}", changes.pop("algo", "csac"), etas=etas, seeds=seeds,
                                  first_seed=args.first_seed, total_steps=total_steps, **changes),
                     args.run_folder(folder, seeds), keep_checkpoints=args.keep_checkpoints)
    found = load(out, plan.runs)
    if not found:
        raise SystemExit(f"error: out: no runs in {out.resolve()}; train them first (without --plot-only)")
    first = next(run for folder in plan.runs for run in seed_folders(out, folder) if (run / "config.json").exists())
    episodes = outputs.read_config(first).budget.eval_episodes
    milestones = args.milestones or plan.milestones
    text = ("Mean evaluation success over seeds (in parentheses: seeds that reached that step), single evaluations "
            f"of {episodes} deterministic episodes:\n\n"
            + "\n".join(milestone_table(found, milestones, with_prototype=args.rooms == 2))
            + "\n\nPer seed (seeds in order; final success = mean of the last 10 evaluations):\n\n"
            + "\n".join(seed_table(found)) + "\n")
    write_text(out / "table.md", text)
    figure(found, args.rooms, out / "success.png")
    print(text)
    return text


if __name__ == "__main__":
    cli(main, Args, largest_grid=largest_grid)
