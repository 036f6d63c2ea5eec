"""How many devices a CPU offers the grid, and how many of them a grid uses.

On a CPU, XLA exposes one device by default, and one grid member's update
(a few hundred small ops at [64, 64]) keeps only part of a second core busy.
Split into several XLA devices, the grid's members run side by side, one per
device, and a grid that does not divide over the cores can take one device
per member instead of computing padded copies (`grid_devices`). Measured with
`experiments/bench/cpu_devices.py` on this project's 2-core CPU, paper epoch:
12 members 1.45× and 3 members 1.52× the runs per second of one device.
Results do not depend on it beyond float rounding (`tests/test_multidevice.py`).
"""
from __future__ import annotations

import math
import os
from typing import Literal, Sequence, Union

import jax
import numpy as np

CPU_DEVICES = "xla_force_host_platform_device_count"  # the XLA flag that splits the host CPU into devices
CpuDevices = Union[int, Literal["auto"]]


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def cpu_device_flags(flags: str, devices: int) -> str:
    """$XLA_FLAGS `flags` with the host CPU split into `devices` devices; a count already in `flags` is kept."""
    if CPU_DEVICES in flags:
        return flags
    return (flags + f" --{CPU_DEVICES}={devices}").strip()


def split_host_cpu(devices: CpuDevices = "auto", grid_size: int | None = None) -> bool:
    """Before JAX starts: expose `devices` CPU devices to this process.

    "auto" with a `grid_size`: exactly the count `grid_devices` picks for that grid of up to twice the
    available cores (`cpu_devices_for`), so that no device sits idle: an exposed device the grid leaves
    unused slowed the others (2-core CPU, SPEC §7's epoch: one 3-room run 2.65–3.0 s per epoch on the
    unsplit CPU, 3.4–4.1 s with 4 devices exposed; a 2-room grid of 3 on 3 devices 3.9–4.0 s with 3
    exposed, 4.4–4.7 s with 4). "auto" without a grid size (a process that cannot say which grids it will
    train): twice the available cores. Returns False, changing nothing, once JAX's backends are running (the flag is read
    when they start). A count the user set in $XLA_FLAGS wins. Accelerators are unaffected: only the CPU
    platform splits, and the grid goes to the default backend's devices.
    """
    from jax._src import xla_bridge  # no public API says whether the backends have started

    if xla_bridge.backends_are_initialized():
        return False
    if devices != "auto":
        count = int(devices)
    elif grid_size is None:
        count = 2 * available_cores()
    else:
        count = cpu_devices_for(grid_size)
    os.environ["XLA_FLAGS"] = cpu_device_flags(os.environ.get("XLA_FLAGS", ""), count)
    return True


def epoch_cost(grid_size: int, used: int, cores: int | None) -> float:
    """Relative time of an epoch of `grid_size` members on `used` devices: each device runs its share (padded
    slots included) one member after another. CPU devices beyond `cores` share them; `cores` None: every
    device has its own (accelerators), so the cost is the share alone."""
    return math.ceil(grid_size / used) * used / (used if cores is None else min(used, cores))


def cheapest_count(grid_size: int, available: int, cores: int | None) -> int:
    """Of 1..`available` devices, the count with the least `epoch_cost` for `grid_size` members, the fewer on a tie."""
    return min(range(1, available + 1), key=lambda d: (epoch_cost(grid_size, d, cores), d))


def cpu_devices_for(grid_size: int, cores: int | None = None) -> int:
    """The CPU devices a grid of `grid_size` members trains on, of up to twice the `cores` (default: those
    available): what `grid_devices` picks when the CPU offers that many. Needs no JAX."""
    cores = cores or available_cores()
    return cheapest_count(grid_size, 2 * cores, cores)


def grid_devices(grid_size: int, devices: Sequence[jax.Device] | None = None,
                 cores: int | None = None) -> list[jax.Device]:
    """The devices (a prefix of `devices`, default all) a grid of `grid_size` members trains on: the count
    with the least `epoch_cost`, the fewer on a tie. `cores` of a CPU default to those available.

    On a CPU that weighs padded copies against cores shared. Measured on 2 cores with the paper's epoch
    (`experiments/bench/cpu_devices.py`): 3 members train 1.52× faster on 3 devices than on one, and not
    faster on 2 (padded to 4: the copy costs a member's time); 12 members 1.45× on 2 devices, 1.25× on 4.
    On accelerators it is the fewest devices with the smallest share (a grid of 6 on 4 GPUs uses 3). With
    several processes every device is kept: each process must own a part of the grid.
    """
    devices = list(devices or jax.devices())
    if jax.process_count() > 1:
        return devices
    cores = (cores or available_cores()) if devices[0].platform == "cpu" else None  # accelerators share none
    return devices[: cheapest_count(grid_size, len(devices), cores)]


def pad_grid(x, size: int) -> np.ndarray:
    """`x` (grid axis first) padded to `size` members with copies of its last: what the slots of a grid that does
    not divide over its devices hold (their results are dropped)."""
    x = np.asarray(x)
    return np.concatenate([x, np.repeat(x[-1:], size - len(x), axis=0)])
