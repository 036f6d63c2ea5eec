"""How many devices a CPU offers the grid, and how many of them a grid uses.

On a CPU, XLA exposes one device by default, and one grid member's update
(a few hundred small ops at [64, 64]) keeps only part of a second core busy.
Split into one XLA device per core, the grid's members run side by side, one
per core (`experiments/bench/cpu_devices.py`: on this project's 2-core CPU,
1.6 – 1.7× the runs per second for grids of 2 and 4). Results do not depend on
it beyond float rounding (`tests/test_multidevice.py`).
"""
from __future__ import annotations

import math
import os
from typing import Literal, Sequence, Union

import jax

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


def split_host_cpu(devices: CpuDevices = "auto") -> bool:
    """Before JAX starts: expose `devices` CPU devices ("auto": one per available core) to this process.

    Returns False, changing nothing, once JAX's backends are running (the flag is read when they start).
    A count the user set in $XLA_FLAGS wins. Accelerators are unaffected: only the CPU platform splits,
    and the grid goes to the default backend's devices.
    """
    from jax._src import xla_bridge  # no public API says whether the backends have started

    if xla_bridge.backends_are_initialized():
        return False
    count = available_cores() if devices == "auto" else int(devices)
    os.environ["XLA_FLAGS"] = cpu_device_flags(os.environ.get("XLA_FLAGS", ""), count)
    return True


def grid_devices(grid_size: int, devices: Sequence[jax.Device] | None = None) -> list[jax.Device]:
    """The fewest of `devices` (default: all) that hold `grid_size` members with the same share per device.

    A grid of 1 on 2 devices uses 1 (no padded copy to compute), 6 on 4 uses 3 (2 each, as on 4). With
    several processes every device is kept: each process must own a part of the grid.
    """
    devices = list(devices or jax.devices())
    if jax.process_count() > 1:
        return devices
    share = math.ceil(grid_size / len(devices))
    return devices[: math.ceil(grid_size / share)]


def resume_devices(grid_size: int, slots: int, devices: Sequence[jax.Device] | None = None) -> list[jax.Device] | None:
    """The most of `devices` (default: all) over which `grid_size` members pad to `slots`, a checkpoint's
    grid size (the members padded for the devices it was saved from); None if no number of them does."""
    devices = list(devices or jax.devices())
    if jax.process_count() > 1:
        return devices
    fits = [d for d in range(1, len(devices) + 1) if math.ceil(grid_size / d) * d == slots]
    return devices[: max(fits)] if fits else None
