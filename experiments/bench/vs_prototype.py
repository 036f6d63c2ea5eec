"""The speed yardstick (docs/design.md#the-learning-yardstick) in one command: our epoch against the prototype's published epoch times.

    python experiments/bench/vs_prototype.py            # ≈ 5 min on a 2-core CPU with nothing else running

The yardstick's settings: CSAC, [64, 64] networks, batch 256, buffer 2e5 per agent,
the paper's epoch (5000 env steps from 1 env, 1000 joint updates, 10
deterministic evaluation episodes of ≤ 1000 steps; an untrained policy uses
all of them). The prototype's figures: 2.5 s per epoch for one 3-room run,
≈ 4 s for the 2-room vmapped grid of 3 seeds.

Each configuration is the real grid trainer (`TimedGrid`) in a process of
its own, with the CPU split as `python -m ccp_jax.train` splits it for that
grid (`--cpu-devices auto`: one run keeps the CPU as one device, a grid of 3
takes 3 devices on 2 cores); the grid of 3 on one device, vmapped (the
prototype's layout), is timed beside it. Processes alternate over the
configurations `pairs` times, `reps` epochs each after compiling, so drift of
a shared machine falls on all of them; figures are medians over all epochs.

Machines differ in speed, and this one's varies by 1.5× between days, so the
script also measures the 256-wide `jnp.dot` roof (a jitted chain of [256, 256]
products, in every process before and after its epochs) and scales our times
to the roof of 148 GFLOP/s measured on the machine the prototype's figures
come from (docs/design.md#the-learning-yardstick): a time scaled that way is what this epoch would take on a machine
as fast as that one.
"""
from __future__ import annotations

import dataclasses
import json
import statistics
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from ccp_jax.devices import CpuDevices, split_host_cpu  # noqa: E402
from grid_scaling import EpochShape, config_for  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402

PROTOTYPE_ROOF_GFLOPS = 148.0  # the 256-wide jnp.dot roof of the machine the prototype's times come from


class Setup(NamedTuple):
    """One timed configuration: the prototype's figure it is compared with, and how we run it."""

    figure: str  # the prototype's configuration
    prototype_s: float  # the prototype's seconds per epoch for it
    layout: str
    rooms: int
    grid: int
    split: CpuDevices  # the CPU split (`split_host_cpu`)
    members_at_once: int | None


CONFIGS = {
    "3 rooms, one run": Setup("3 rooms, one run", 2.5, "one run", 3, 1, "auto", None),
    "2 rooms, grid of 3": Setup("2 rooms, grid of 3", 4.0, "the CLI's (CPU split)", 2, 3, "auto", None),
    "2 rooms, grid of 3, one device": Setup("2 rooms, grid of 3", 4.0, "one device, vmapped", 2, 3, 1, 3),
}


@dataclasses.dataclass
class Args:
    reps: int = 5
    """Timed epochs per configuration and process."""
    pairs: int = 2
    """Processes per configuration, alternating."""
    steps_per_epoch: int = 5000
    loops: int = 1000
    eval_episodes: int = 10
    episode_length: int = 1000
    """The epoch; the defaults are the yardstick's (smaller values only to try the script quickly)."""
    worker: str = ""
    """Internal: time this configuration in this process and print JSON."""


def scaled(epoch_s: float, roof_gflops: float) -> float:
    """`epoch_s` measured under a roof of `roof_gflops`, as it would be under the prototype machine's roof."""
    return epoch_s * roof_gflops / PROTOTYPE_ROOF_GFLOPS


def report(rows: list[dict]) -> str:
    """A markdown table: rows {name, devices, epochs: [s, ...], roofs: [GFLOP/s measured around them]}."""
    lines = ["| configuration | layout | devices | ours, s per epoch (median, min–max) | 256-wide roof, GFLOP/s "
             "| prototype | ours / prototype | ours at the prototype machine's roof (148) | ours / prototype there |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        setup = CONFIGS[r["name"]]
        proto = setup.prototype_s
        median, roof = statistics.median(r["epochs"]), statistics.median(r["roofs"])
        at_spec = scaled(median, roof)
        lines.append(f"| {setup.figure} | {setup.layout} | {r['devices']} | {median:.2f} "
                     f"({min(r['epochs']):.2f}–{max(r['epochs']):.2f}) | {roof:.0f} | {proto:.1f} | "
                     f"{median / proto:.2f} | {at_spec:.2f} | {at_spec / proto:.2f} |")
    return "\n".join(lines)


def worker(args: Args) -> None:
    from timed import emitters_on_everywhere

    setup = CONFIGS[args.worker]
    emitters_on_everywhere()  # before JAX starts: the roof compiled as the maze epoch is
    split_host_cpu(setup.split, setup.grid)
    from timed import TimedGrid
    from update_speed import matmul_roof

    shape = EpochShape(steps_per_epoch=args.steps_per_epoch, loops=args.loops, eval_episodes=args.eval_episodes,
                       episode_length=args.episode_length, buffer=200_000)
    roofs = [matmul_roof(256, 256, reps=5) / 1e9]
    run = TimedGrid(config_for(shape, setup.rooms, setup.grid), members_at_once=setup.members_at_once)
    for _ in range(args.reps):
        run.epoch()
    roofs.append(matmul_roof(256, 256, reps=5) / 1e9)
    print(json.dumps({"devices": len(run.trainer.devices), "epochs": run.times, "roofs": roofs,
                      "compile_s": run.compile_s}))


def main(args: Args) -> str:
    rows = {name: {"name": name, "epochs": [], "roofs": []} for name in CONFIGS}
    for pair in range(args.pairs):
        for name in CONFIGS:
            argv = [sys.executable, __file__, "--worker", name] + [
                f"--{k.replace('_', '-')}={v}" for k, v in dataclasses.asdict(args).items() if k != "worker"]
            done = subprocess.run(argv, capture_output=True, text=True, check=True)
            out = json.loads(done.stdout.strip().splitlines()[-1])
            rows[name].update(devices=out["devices"])
            rows[name]["epochs"] += out["epochs"]
            rows[name]["roofs"] += out["roofs"]
            print(f"pair {pair}, {name}: compile {out['compile_s']:.1f} s, epochs "
                  + " ".join(f"{t:.2f}" for t in out["epochs"]) + f" s, roof {statistics.median(out['roofs']):.0f}",
                  flush=True)
    text = report(list(rows.values()))
    print(text)
    return text


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    parsed = tyro.cli(Args)
    worker(parsed) if parsed.worker else main(parsed)
