"""Our grid trainer against the plain reference CSAC (experiments/crosscheck) on the same work.

Both train the 2-room yardstick's epoch (docs/design.md#the-learning-yardstick) (5000 env steps, 1000 joint
updates, 10 evaluation episodes; [64, 64] nets, batch 256, buffer 2e5) for G
seeds in one compiled program: ours with members one at a time and all
vmapped, the reference with its seeds vmapped. Epochs are timed round-robin
(one epoch of each contender per round, so load drifts hit all alike);
medians of the warm rounds, compile reported apart.

    python experiments/bench/vs_reference.py --grids 1 6 --rounds 3
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "crosscheck"))
from reference_csac import Settings, make_run  # noqa: E402
from timed import TimedEpochs, TimedGrid, emitters_on_everywhere  # noqa: E402

from ccp_jax.config import make_config  # noqa: E402
from envs_mjx.maze import Maze  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class Args:
    grids: tuple[int, ...] = (1, 6)
    rounds: int = 3


class TimedReference(TimedEpochs):
    """The reference's vmapped epoch over `grid` seeds, compiled and warmed."""

    def __init__(self, grid: int):
        init, epoch = make_run(Settings(), Maze(rooms=2))
        self.state = jax.block_until_ready(jax.vmap(init)(jnp.arange(grid)))
        self.step = jax.jit(jax.vmap(epoch))
        self.times = []
        self.compile_s = self.epoch() - self.epoch()
        self.times.clear()

    def _step(self):
        self.state, metrics = self.step(self.state)
        return self.state, metrics


def main(args: Args) -> None:
    for grid in args.grids:
        config = make_config("small", rooms=2, algo="csac", etas=((0.1,),), seeds=tuple(range(grid)), total_steps=200_000)
        runs = {"reference (vmapped)": TimedReference(grid),
                "ours, one at a time": TimedGrid(config, members_at_once=1)}
        if grid > 1:
            runs["ours, vmapped"] = TimedGrid(config, members_at_once=grid)
        for _ in range(args.rounds):
            for run in runs.values():
                run.epoch()
        ref = runs["reference (vmapped)"].median / grid
        print(f"\nG = {grid} (2-room CSAC epoch, median of {args.rounds} rounds)")
        print("| contender | s per run-epoch | vs reference | compile s |\n|---|---|---|---|")
        for name, run in runs.items():
            per_run = run.median / grid
            print(f"| {name} | {per_run:.2f} | {ref / per_run:.2f}x | {run.compile_s:.0f} |")


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    emitters_on_everywhere()  # both sides compile alike (timed.py)
    main(tyro.cli(Args))
