"""How an epoch's wall time scales with the grid size G (runs trained in one program) and the number of agents N.

    python experiments/bench/grid_scaling.py                          # G = 1..32 at N = 3, then N = 1..4 at G = 1
    python experiments/bench/grid_scaling.py --modes vmap             # only the whole grid vmapped (the GPU default)
    python experiments/bench/grid_scaling.py --grids 1 4 16 --agents  # grid sweep only
    python experiments/bench/grid_scaling.py --breakdown              # also split epochs into collect / update / eval

Every configuration is the real grid trainer (`make_grid_train`) of one
process, on the maze, with the "small" preset ([64, 64] nets, batch 256) and
a shortened epoch so that 32 runs finish in seconds: `steps_per_epoch` env
steps (1 env), `loops` joint updates (the paper's 1 update per 5 env steps),
evaluation of `eval_episodes` deterministic episodes of at most
`episode_length` steps (an untrained policy uses all of them), buffers of
`buffer` transitions per agent. Every configuration is built and run
once first (that epoch compiles; its time minus the median epoch is the
compile time); then epochs of all configurations are timed round-robin,
`reps` rounds, each to `block_until_ready`, and each figure is the median of
its configuration's epochs, so a change of load on a shared machine spreads
over all configurations instead of landing on one.

Each grid size runs in two modes (`--modes`): `one`, members one after
another inside the compiled program (`members_at_once=1`, the CPU default),
and `vmap`, all G members vmapped together (the GPU default).

Columns: epoch s = one call of `train_step` for the whole grid; per run =
epoch s / G; speed-up = G · epoch(G=1) / epoch(G), i.e. how many times more
runs per second the grid gives than one run at a time.
N = 1 is end-to-end SAC (one agent); N >= 2 is CSAC on an N-room maze.
With `--breakdown` each configuration is also run with evaluation stubbed out
and with a single update per epoch, which splits the epoch into collection,
updates and evaluation (by difference).
"""
from __future__ import annotations

import dataclasses
import sys
from typing import Literal
from pathlib import Path

import jax
import tyro

from ccp_jax.config import make_config

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timed import TimedGrid  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class EpochShape:
    """A shortened epoch with the paper's 5 env steps per update (shared with cpu_devices.py)."""

    preset: str = "small"
    hidden: tuple[int, ...] = (64, 64)
    steps_per_epoch: int = 500
    loops: int = 100
    eval_episodes: int = 5
    episode_length: int = 200
    buffer: int = 10_000
    reps: int = 3


@dataclasses.dataclass
class Args(EpochShape):
    grids: tuple[int, ...] = (1, 2, 4, 8, 16, 32)
    """Grid sizes G for the grid sweep (at `grid_agents` agents); empty to skip."""
    grid_agents: int = 3
    modes: tuple[Literal["one", "vmap"], ...] = ("one", "vmap")
    """Grid modes: members one at a time (members_at_once=1) and/or all vmapped (members_at_once=G)."""
    agents: tuple[int, ...] = (1, 2, 3, 4)
    """Agent counts N for the agent sweep (at G = `agents_grid`); empty to skip."""
    agents_grid: int = 1
    breakdown: bool = False


def config_for(args: EpochShape, n_agents: int, grid: int, **overrides):
    algo, rooms = ("sac", 2) if n_agents == 1 else ("csac", n_agents)
    fields = dict(algo=algo, rooms=rooms, hidden=args.hidden, steps_per_epoch=args.steps_per_epoch,
                  train_loops_per_epoch=args.loops, num_envs=1, start_steps=0, eval_episodes=args.eval_episodes,
                  max_episode_steps=args.episode_length, buffer_size=args.buffer, seeds=tuple(range(grid)),
                  total_steps=100 * args.steps_per_epoch)
    return make_config(args.preset, **{**fields, **overrides})


def build(args: Args, n_agents: int, grid: int, mode: str) -> dict[str, TimedGrid]:
    at_once = 1 if mode == "one" else grid
    runs = {"full": TimedGrid(config_for(args, n_agents, grid), members_at_once=at_once)}
    if args.breakdown:
        runs["no_eval"] = TimedGrid(config_for(args, n_agents, grid), evaluate=False, members_at_once=at_once)
        runs["collect"] = TimedGrid(config_for(args, n_agents, grid, train_loops_per_epoch=1), evaluate=False,
                                    members_at_once=at_once)
    return runs


def row_of(n_agents: int, grid: int, mode: str, runs: dict[str, TimedGrid]) -> dict:
    full = runs["full"]
    row = {"agents": n_agents, "grid": grid, "mode": mode, "epoch_s": full.median, "compile_s": full.compile_s,
           "epochs": full.times, "recompiled_s": full.second - full.median if full.retraced else 0.0,
           "retraced": full.retraced}
    if "collect" in runs:
        no_eval, collect = runs["no_eval"].median, runs["collect"].median
        row.update(collect_s=collect, update_s=no_eval - collect, eval_s=full.median - no_eval)
    return row


def print_rows(rows: list[dict], args: Args, base: dict) -> None:
    head = f"{'G':>4}{'N':>3}{'mode':>6}{'epoch s':>10}{'per run s':>11}{'speed-up':>10}{'agent-upd/s':>13}{'env steps/s':>13}{'compile s':>11}"
    if args.breakdown:
        head += f"{'collect':>9}{'update':>8}{'eval':>7}"
    print(head)
    for r in rows:
        g, n, e = r["grid"], r["agents"], r["epoch_s"]
        speedup = f"{g * base['epoch_s'] / e:>10.2f}" if base["agents"] == n else f"{'—':>10}"
        line = (f"{g:>4}{n:>3}{r['mode']:>6}{e:>10.2f}{e / g:>11.3f}{speedup}{g * n * args.loops / e:>13.0f}"
                f"{g * args.steps_per_epoch / e:>13.0f}{r['compile_s']:>11.1f}")
        if args.breakdown:
            line += "".join(f"{r[k] / e:>{w}.0%}" for k, w in (("collect_s", 9), ("update_s", 8), ("eval_s", 7)))
        if r.get("retraced"):
            line += f"   + {r['recompiled_s']:.1f} s compiling again in epoch 2"
        print(line)


def main(args: Args) -> dict:
    print(f"preset {args.preset}, hidden {args.hidden}, epoch = {args.steps_per_epoch} env steps (1 env) + "
          f"{args.loops} joint updates + eval {args.eval_episodes} × ≤{args.episode_length} steps; buffers "
          f"{args.buffer}/agent; medians of {args.reps} epochs; devices {jax.devices()}")
    modes = args.modes or ("one",)
    configs = ([("grid", args.grid_agents, g, m) for g in args.grids for m in modes if g > 1 or m == modes[0]]
               + [("agents", n, args.agents_grid, modes[0]) for n in args.agents])
    built = []
    for sweep, n, g, mode in configs:  # compile everything first ...
        built.append((sweep, n, g, mode, build(args, n, g, mode)))
        full = built[-1][4]["full"]
        print(f"  built N={n} G={g} {mode}: first epoch (compile + run) {full.first:.1f} s", flush=True)
        if full.retraced:
            print(f"  WARNING N={n} G={g} {mode}: the state's types changed in the first epoch, so the second epoch "
                  f"compiled again ({full.second:.1f} s): " + "; ".join(full.retraced), flush=True)
    for r in range(args.reps):  # ... then time epochs round-robin, so load changes hit every configuration alike
        for *_, runs in built:
            for run in runs.values():
                run.epoch()
        print(f"  round {r}: " + ", ".join(f"N={n} G={g} {mode} {runs['full'].times[-1]:.2f} s"
                                           for _, n, g, mode, runs in built), flush=True)
    result = {"args": dataclasses.asdict(args), "grid": [], "agents": []}
    for sweep, n, g, mode, runs in built:
        result[sweep].append(row_of(n, g, mode, runs))
    if result["grid"]:
        print(f"\nGrid sweep (N = {args.grid_agents}); speed-up against G = {result['grid'][0]['grid']}:")
        base = result["grid"][0]
        print_rows(result["grid"], args, {**base, "epoch_s": base["epoch_s"] / base["grid"]})
    if result["agents"]:
        print(f"\nAgent sweep (G = {args.agents_grid}); N = 1 is end-to-end SAC:")
        print_rows(result["agents"], args, {"agents": -1, "epoch_s": 1.0})
    return result


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main(tyro.cli(Args))
