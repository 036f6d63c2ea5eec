"""What population-based training costs per epoch: the same grid with and without `--pbt-every`, in one process.

    python experiments/bench/pbt_overhead.py                            # 2-room CSAC, a grid of 8, 6 epochs each
    python experiments/bench/pbt_overhead.py --rooms 3 --seeds 4 --reps 4

Three versions of one grid trainer (the yardstick's settings, docs/design.md#the-learning-yardstick:
"small" preset, [64, 64], the paper's epoch of 5000 env steps and 1000 joint updates, buffer 2e5 per agent):
no PBT; `pbt_every=1`, a ranking (and the copies of whole member states, replay buffers included) after
every epoch, the worst case; and `pbt_every=1000`, which never ranks in the timed epochs but carries
PBT's state and its `lax.cond`. The grid is `len(etas) × seeds` members; every member's whole state is
on one device. Epochs alternate (order reversed every round); the table gives each version's median and
the median of the paired ratios against no PBT.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timed import Alternating, TimedGrid, alternate, emitters_on_everywhere, paired_table  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class Args(Alternating):
    rooms: int = 2
    seeds: int = 2
    """Seeds per ratio."""
    etas: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7)
    reps: int = 6


def main(args: Args) -> None:
    from ccp_jax.config import make_config

    def config(pbt_every: int):
        return make_config("small", rooms=args.rooms, seeds=tuple(range(args.seeds)), buffer_size=200_000,
                           etas=tuple((e,) for e in args.etas), pbt_every=pbt_every)

    versions = {"no PBT": 0, "ranking every epoch": 1, "PBT on, no ranking": 1000}
    runs = {name: TimedGrid(config(every)) for name, every in versions.items()}
    alternate(runs, args.reps)
    size = len(args.etas) * args.seeds
    print(f"\n{args.rooms}-room CSAC, grid of {size}, paper epoch, {args.reps} alternating epochs each\n")
    print(paired_table(runs, "no PBT", "this / no PBT", lambda base, this: this / base))


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    emitters_on_everywhere()  # before JAX computes: every version compiled as the maze epoch is
    main(tyro.cli(Args, description=__doc__))
