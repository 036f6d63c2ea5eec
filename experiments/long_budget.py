"""The 2-room maze at five times the `cpu` scale's budget: do CSAC's traps let go given more steps?

    python experiments/long_budget.py                 # trains (or resumes) the grids, then the table and figure
    python experiments/long_budget.py --plot-only     # table and figure from the runs as they stand

SPEC §7's yardstick settings (the `cpu` scale: [64, 64] nets, the paper's epoch,
buffers of 2e5), seeds 0–5, 750 k env steps (a quarter of the paper's 3 M; the
`cpu` scale's Table I gives the 2-room maze 150 k): CSAC with η = 0.1 (the
paper's best 2-room ratio and SPEC §7's) and `auto`, both with the paper's batch
normaliser (one grid, csac_batch/), `auto` with the floor normaliser
(csac_auto_floor/), and η = 0.5, the `cpu` sweep's best ratio (csac_eta_0.5/).
Writes into the results folder: table.md (mean success at SPEC §7's milestones
beside its prototype's, then per seed the final success, the first success and
where the last evaluations end) and success.png.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ccp_jax import plot
from ccp_jax.config import AUTO
from common import SCALES, ScaleName, cli, final_ends, fmt, mean_std, read_json, run_grid, success_at, write_text

# Run folder -> (ratio grid, config changes); each holds seeds 0..seeds-1. η = 0.5 is the `cpu` scale's best
# swept 2-room ratio (Table I at 150 k), η = 0.1 the paper's.
RUNS = {"csac_batch": (((0.1,), (AUTO,)), {}),
        "csac_auto_floor": (((AUTO,),), {"normaliser": "floor"}),
        "csac_eta_0.5": (((0.5,),), {})}
# SPEC §7: the prototype's mean success (CSAC η = 0.1, 3 seeds) at these env steps; 0.93–1.00 from 250 k to 515 k.
PROTOTYPE = {100_000: 0.03, 150_000: 0.33, 200_000: 0.77}
PROTOTYPE_PLATEAU = (250_000, 515_000, 0.93, 1.00)


@dataclasses.dataclass
class Args:
    scale: ScaleName = "cpu"
    seeds: int = 6
    total_steps: int = 750_000
    milestones: tuple[int, ...] = (50_000, 100_000, 150_000, 200_000, 250_000, 300_000, 400_000, 515_000,
                                   600_000, 750_000)
    """Env steps at which the table gives the mean success over seeds (single evaluations)."""
    out: Path = Path("experiments/results/long_2room")
    plot_only: bool = False
    """Never train: table and figure from whatever the folders hold (unfinished runs too)."""


def variant(eta: tuple, changes: dict) -> str:
    """A row's name: "CSAC η = 0.1", or "auto, floor normaliser"."""
    return f"auto, {changes.get('normaliser', 'batch')} normaliser" if AUTO in eta else f"CSAC η = {eta[0]:g}"


def prototype(steps: int) -> str:
    if steps in PROTOTYPE:
        return f"{PROTOTYPE[steps]:.2f}"
    start, end, low, high = PROTOTYPE_PLATEAU
    return f"{low:.2f}–{high:.2f}" if start <= steps <= end else "–"


def load(out: Path) -> dict[str, dict]:
    """{variant: {"curves": [(steps, success)] per member, "members": summary members or None, "ends": ...}}."""
    found = {}
    for folder, (_, changes) in RUNS.items():
        run = out / folder
        if not (run / "metrics.jsonl").exists():
            continue
        summary = read_json(run / "summary.json") if (run / "summary.json").exists() else None
        ends = final_ends(run) if summary else {}
        for (_, _, eta), series in plot.load_curves([run]).items():
            members = summary and [m for m in summary["members"] if tuple(m["eta"]) == eta]
            found[variant(eta, changes)] = dict(curves=series, members=members,
                                               ends=members and [ends[m["member"]] for m in members])
    return dict(sorted(found.items(), key=lambda item: item[0].startswith("auto")))  # numeric ratios first


def milestone_table(found: dict[str, dict], milestones: tuple[int, ...]) -> list[str]:
    lines = ["| env steps | SPEC §7 prototype (η = 0.1, 3 seeds) | " + " | ".join(found) + " |",
             "|---" * (2 + len(found)) + "|"]
    for steps in milestones:
        cells = []
        for v in found.values():
            at = success_at(v["curves"], steps)
            cells.append(f"{np.mean(at):.2f} ({len(at)})" if at else "–")
        lines.append(f"| {steps:,} | {prototype(steps)} | " + " | ".join(cells) + " |")
    return lines


def seed_table(found: dict[str, dict]) -> list[str]:
    lines = ["| variant | final success | per seed | first success (env steps) | last evaluations end in: "
             "room 2 (fraction in the pocket) |", "|---|---|---|---|---|"]
    for name, v in found.items():
        if not v["members"]:
            continue
        finals = [m["final_success"] for m in v["members"]]
        firsts = " ".join("never" if m["first_success_env_steps"] is None else f"{m['first_success_env_steps']:,}"
                          for m in v["members"])
        ends = " ".join(f"{stage - 1:.2f} ({fmt(pocket)})" for stage, pocket in v["ends"])
        lines.append(f"| {name} | {mean_std(finals)} | {' '.join(f'{x:.2f}' for x in finals)} | {firsts} | {ends} |")
    return lines


def figure(found: dict[str, dict], path: Path) -> None:
    groups = {("maze-2", name, ()): v["curves"] for name, v in found.items()}
    ax = plot.curves(groups, title="2-room maze, [64, 64]").axes[0]
    ax.plot(list(PROTOTYPE), list(PROTOTYPE.values()), "ko--", label="SPEC §7 prototype, η = 0.1 (3 seeds)")
    start, end, low, high = PROTOTYPE_PLATEAU
    ax.fill_between([start, end], low, high, color="k", alpha=0.25, linewidth=0)
    ax.legend(fontsize="small")
    ax.figure.savefig(path)


def main(args: Args) -> str:
    scale = SCALES[args.scale]
    if not args.plot_only:
        for folder, (etas, changes) in RUNS.items():
            run_grid(scale.config("maze2", "csac", etas=etas, seeds=args.seeds, total_steps=args.total_steps,
                                  **changes), args.out / folder)
    found = load(args.out)
    if not found:
        raise SystemExit(f"error: out: no runs in {args.out}; train them first (without --plot-only)")
    episodes = read_json(args.out / next(iter(RUNS)) / "config.json")["eval_episodes"]
    text = ("Mean evaluation success over seeds (in parentheses: seeds that reached that step), single evaluations "
            f"of {episodes} deterministic episodes:\n\n" + "\n".join(milestone_table(found, args.milestones))
            + "\n\nPer seed (seeds in order; final success = mean of the last 10 evaluations):\n\n"
            + "\n".join(seed_table(found)) + "\n")
    write_text(args.out / "table.md", text)
    figure(found, args.out / "success.png")
    print(text)
    return text


if __name__ == "__main__":
    cli(main, Args)
