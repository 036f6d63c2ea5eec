"""How many devices a CPU offers the grid, and how many of them a grid uses.

On a CPU, XLA exposes one device by default, and one grid member's update
(a few hundred small ops at [64, 64]) keeps only part of a second core busy.
Split into several XLA devices, the grid's members run side by side, one per
device, and a grid that does not divide over the cores can take one device
per member instead of computing padded copies (`grid_devices`). Measured with
`experiments/bench/cpu_devices.py` on this project's 2-core CPU, paper epoch:
12 members 1.45× and 3 members 1.52× the runs per second of one device.
Results do not depend on it beyond float rounding (`tests/test_multidevice.py`).

Also here, the other choices measured on CPUs only: how many grid members one
device advances together (`default_members_at_once`) and the compile options
of the run's init (`CPU_INIT_OPTIONS`).
"""
from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING, Literal, Sequence, Union

import jax
import numpy as np

if TYPE_CHECKING:
    from ccp_jax.config import Config

CPU_DEVICES = "xla_force_host_platform_device_count"  # the XLA flag that splits the host CPU into devices
CpuDevices = Union[int, Literal["auto"]]


def host_cpu_tag() -> str:
    """A short name for this host's CPU model and instruction-set features (12 hex digits).

    Compiled CPU programs use every feature of the CPU that compiled them; one loaded on a CPU without them can
    die of SIGILL. The default compile cache is kept per tag, so a home folder shared by different machines
    never hands one machine another's programs.
    """
    import hashlib
    import platform

    described = platform.machine() + platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            lines = f.read().splitlines()
        described += "".join(sorted({line for line in lines if line.startswith(("model name", "flags", "Features"))}))
    except OSError:  # not Linux: the machine and processor names alone
        pass
    return hashlib.sha1(described.encode()).hexdigest()[:12]


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
    unused slowed the others (2-core CPU, docs/design.md#the-learning-yardstick's epoch: one 3-room run 2.65–3.0 s per epoch on the
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


# The init runs once; on a CPU its program (mostly the networks' random initialisers, vmapped) compiles 2-5x
# faster at LLVM's O1 (experiments/bench/init_compile.py): the same bits on the maze, MJX's reset by ulps.
CPU_INIT_OPTIONS = {"xla_backend_optimization_level": 1}


# On a CPU, how many floats one layer's stacked critic activations of a device's vmapped members may take
# (members × critic slots × batch × widest layer): 12 slots of the learning yardstick's [64, 64] at batch 256
# (docs/design.md#the-learning-yardstick), ≈ 0.75 MB. Measured on the 2-core CPU (experiments/bench/README.md, "Members vmapped on a CPU").
CPU_VMAP_FLOATS = 12 * 256 * 64


def default_members_at_once(devices: Sequence[jax.Device], local_members: int, config: Config,
                            cores_per_device: float | None = None) -> int:
    """How many grid members one device advances together (vmapped) by default.

    On a GPU/TPU all of them: the batching fills the device. On a CPU device
    with several cores (`cores_per_device`, default: the available cores over
    the process's CPU devices) as many as keep one layer's stacked critic
    activations within `CPU_VMAP_FLOATS`: XLA runs a small run's ops one core
    each, and vmapped members' larger ops use the cores better (a [64, 64] SAC
    grid of 4 on one 2-core device: 1.4× faster than one at a time), until the
    batched working set leaves the cache (3-agent CSAC, 16 members: each update
    ≈ 20 % slower). On a CPU split into a device per core (the CLI's split for
    grids) one member at a time: there vmapping was 7–10 % slower.
    """
    from ccp_jax.learner import critic_slots  # local: this module loads before JAX starts and stays light

    if devices[0].platform != "cpu":
        return local_members
    if cores_per_device is None:
        cores_per_device = available_cores() / len(jax.local_devices(backend="cpu"))
    if cores_per_device < 2:
        return 1
    per_member = critic_slots(config) * config.sac.batch_size * max(config.sac.hidden)
    return max(1, CPU_VMAP_FLOATS // per_member)
