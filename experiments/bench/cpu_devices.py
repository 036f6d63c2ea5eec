"""A grid's epoch with the CPU as one XLA device against the CLI's split (`--cpu-devices auto`: twice the cores).

    python experiments/bench/cpu_devices.py                              # grids of 1, 2, 3, 4, 12 on the 2-room maze
    python experiments/bench/cpu_devices.py --rooms 3 --grids 1 3 \\
        --steps-per-epoch 5000 --loops 1000 --eval-episodes 10 --episode-length 1000 --buffer 200000   # the yardstick's epoch

The device count is fixed when JAX starts, so each count runs in its own
process (this script, `--worker`), which builds and compiles the real grid
trainer for every grid size, then times `reps` epochs of each round-robin.
Processes for the two counts alternate `pairs` times, so drift of a shared
machine falls on both; every figure is a median over all epochs of its
configuration. Each grid uses the devices `ccp_jax.devices.grid_devices`
picks of those exposed (column `devices used`). Columns: epoch s per device
count, and how many times more runs per second the split gives (`speed-up` = epoch on one device / epoch
split). Settings as `grid_scaling.py` ([64, 64] nets, a shortened epoch with
the paper's 5 env steps per update, CSAC on the N-room maze).
"""
from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from ccp_jax.devices import CPU_DEVICES, available_cores  # noqa: E402
from grid_scaling import EpochShape, config_for  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class Args(EpochShape):
    grids: tuple[int, ...] = (1, 2, 3, 4, 12)
    """Grid sizes G (members trained in one program)."""
    rooms: int = 2
    devices: int = 0
    """Devices to split the CPU into (0: the CLI's auto, twice the available cores); compared with 1."""
    pairs: int = 2
    """Processes per device count, alternating."""
    worker: int = 0
    """Internal: time the grids in this process (its device count is already set) and print JSON."""


def worker(args: Args) -> None:
    import jax
    from timed import TimedGrid

    assert jax.device_count() == args.worker, jax.devices()
    runs = {g: TimedGrid(config_for(args, args.rooms, g)) for g in args.grids}
    for _ in range(args.reps):
        for run in runs.values():
            run.epoch()
    print(json.dumps({"devices": {g: len(r.trainer.devices) for g, r in runs.items()},
                      "epochs": {g: r.times for g, r in runs.items()}}))


def spawn(args: Args, devices: int) -> dict:
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if CPU_DEVICES not in f)
    env = dict(os.environ, XLA_FLAGS=f"{flags} --{CPU_DEVICES}={devices}".strip(), JAX_PLATFORMS="cpu")
    argv = [sys.executable, __file__, "--worker", str(devices), "--rooms", str(args.rooms), "--reps", str(args.reps),
            "--steps-per-epoch", str(args.steps_per_epoch), "--loops", str(args.loops), "--eval-episodes",
            str(args.eval_episodes), "--episode-length", str(args.episode_length), "--buffer", str(args.buffer),
            "--preset", args.preset, "--hidden", *map(str, args.hidden), "--grids", *map(str, args.grids)]
    done = subprocess.run(argv, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(done.stderr[-3000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(args: Args) -> dict:
    split = args.devices or 2 * available_cores()
    print(f"{args.rooms}-room CSAC, [64, 64], epoch = {args.steps_per_epoch} env steps + {args.loops} updates + eval "
          f"{args.eval_episodes} × ≤{args.episode_length} steps; 1 device against {split}, {args.pairs} alternating "
          f"processes each, {args.reps} epochs per configuration and process", flush=True)
    epochs = {1: {g: [] for g in args.grids}, split: {g: [] for g in args.grids}}
    used = {}
    for pair in range(args.pairs):
        for count in (1, split):
            result = spawn(args, count)
            used[count] = result["devices"]
            for g, times in result["epochs"].items():
                epochs[count][int(g)] += times
            print(f"  pair {pair}, {count} device(s): " + ", ".join(
                f"G={g} {statistics.median(t):.2f} s" for g, t in result["epochs"].items()), flush=True)
    print(f"\n{'G':>4}{'epoch s, 1 device':>20}{f'epoch s, {split} devices':>22}{'devices used':>14}{'speed-up':>10}")
    table = []
    for g in args.grids:
        one, many = statistics.median(epochs[1][g]), statistics.median(epochs[split][g])
        table.append({"grid": g, "one_s": one, "split_s": many, "speedup": one / many,
                      "devices_used": used[split][str(g)]})
        print(f"{g:>4}{one:>20.2f}{many:>22.2f}{used[split][str(g)]:>14}{one / many:>10.2f}")
    return {"args": dataclasses.asdict(args), "table": table}


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    parsed = tyro.cli(Args)
    if parsed.worker:
        worker(parsed)
    else:
        main(parsed)
