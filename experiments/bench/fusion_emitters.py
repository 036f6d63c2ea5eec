"""The trainer's maze epoch compiled with XLA's CPU fusion emitters on (what it does) against off (the process flag).

    python experiments/bench/fusion_emitters.py                      # 3-room CSAC, one run (the speed yardstick, docs/design.md#the-learning-yardstick)
    python experiments/bench/fusion_emitters.py --rooms 2 --seeds 3  # 2-room grid of 3, members one at a time

`envs_mjx.configure_cpu()` (called first, as by the CLI) turns the emitters off process-wide (MJX needs it), and the
trainer compiles its epoch with them back on for an env that does not run MJX
(`envs_mjx.cpu_compiler_options`). Both versions of the same grid trainer (the yardstick's settings, docs/design.md#the-learning-yardstick: "small" preset,
[64, 64], the paper's epoch of 5000 env steps and 1000 joint updates, buffer 2e5, 10 evaluation episodes) are
compiled in this one process; their epochs alternate (order swapped every round) and the table gives each one's
median and the median of the paired ratios on/off.
"""
from __future__ import annotations

import statistics
import sys
from pathlib import Path
from unittest import mock

import tyro

import ccp_jax.grid as grid_module

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timed import Alternating, TimedGrid  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


def main(args: Alternating) -> None:
    config = args.config()
    with mock.patch.object(grid_module, "cpu_compiler_options", lambda env: {}):
        off = TimedGrid(config)
    on = TimedGrid(config)
    assert on.trainer.compiler_options and not off.trainer.compiler_options
    for r in range(args.reps):
        for timed in ((off, on) if r % 2 == 0 else (on, off)):
            timed.epoch()
    ratios = [a / b for a, b in zip(on.times, off.times)]
    print(f"\n{args.rooms}-room CSAC, grid of {args.seeds}, paper epoch, {args.reps} alternating epochs each")
    print(f"{'emitters':>9} {'epoch s (median)':>17} {'min':>6} {'max':>6} {'compile s':>10}")
    for name, timed in (("off", off), ("on", on)):
        print(f"{name:>9} {timed.median:17.3f} {min(timed.times):6.2f} {max(timed.times):6.2f} {timed.compile_s:10.1f}")
    print(f"on / off, median of the paired ratios: {statistics.median(ratios):.3f} "
          f"(min {min(ratios):.3f}, max {max(ratios):.3f})")


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main(tyro.cli(Alternating, description=__doc__))
