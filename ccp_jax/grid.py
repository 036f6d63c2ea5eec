"""The grid: a `Trainer` mapped over seeds × ratios, jitted, and sharded over devices.

The grid axis (docs/design.md#the-trainer) is split across devices with a 1-D
mesh; on each device, groups of members are vmapped together and the groups
run one after another inside the same compiled program. `devices` decides how
many devices and how many members at once; this module builds the program.
"""
from __future__ import annotations

from typing import Sequence

import jax
import numpy as np
from brax.envs.base import Env
from jax.sharding import Mesh, NamedSharding, PartitionSpec, SingleDeviceSharding

from ccp_jax.config import Config, ConfigError
from ccp_jax.devices import CPU_INIT_OPTIONS, default_members_at_once, grid_devices, pad_grid
from ccp_jax.pbt import init_member, pbt_step
from ccp_jax.trainer import EpochMetrics, Trainer, TrainState, make_train
from envs_mjx import cpu_compiler_options


def check_members_at_once(members_at_once: int | None) -> None:
    """Refuses a group size below 1 (None means the default), naming the field."""
    if members_at_once is not None and members_at_once < 1:
        raise ConfigError("members_at_once", f"must be >= 1, got {members_at_once}")


class GridTrainer:
    """A `Trainer` mapped over the grid axis, jitted, and sharded over devices.

    The grid axis (seeds × ratios) is split across `devices` (default: those
    `grid_devices` picks of the visible ones) with a 1-D mesh (one device: no
    mesh, a plain `jit`); a grid that does not divide evenly is padded with
    copies of its last member, whose results are dropped. On each device, `members_at_once`
    members (rounded down to a divisor of the device's share) are vmapped
    together, and such groups run one after another inside the same compiled
    program (`jax.lax.map`); the default is `default_members_at_once`. Results
    do not depend on it beyond float rounding. `train_step` donates the state,
    so the replay buffers are updated in place.

    With `pbt_every` (population-based training, `ccp_jax.pbt`) each member's state carries its ratios,
    starting from the grid's, and the same program ends each epoch with the PBT step across the grid axis.
    """

    def __init__(self, config: Config, env: Env, devices: Sequence[jax.Device] | None = None,
                 trainer: Trainer | None = None, members_at_once: int | None = None):
        trainer = make_train(config, env) if trainer is None else trainer  # e.g. TP brings its own
        self.networks = trainer.networks
        self.devices = list(devices) if devices else grid_devices(config.grid_size)
        self.grid_size = config.grid_size
        self.pbt = config.ccp.pbt_every > 0
        self._eta = config.grid_arrays()[0]  # PBT's starting ratios
        self.padded_size = -(-self.grid_size // len(self.devices)) * len(self.devices)
        local = self.padded_size // len(self.devices)
        check_members_at_once(members_at_once)
        wanted = min(members_at_once or default_members_at_once(self.devices, local, config), local)
        self.members_at_once = max(k for k in range(1, wanted + 1) if local % k == 0)  # equal groups
        # One device needs no mesh: then the env's calls share one trace (`TracedOnce`). Under shard_map
        # they cannot: the carried env state is typed varying over the grid axis where a fresh reset's
        # constant leaves (done, steps, ...) are not, and init runs outside the mesh's context.
        one = len(self.devices) == 1
        mesh, spec = (None, None) if one else (Mesh(np.array(self.devices), ("grid",)), PartitionSpec("grid"))
        self.sharding = SingleDeviceSharding(self.devices[0]) if one else NamedSharding(mesh, spec)
        step = _local_step(trainer, local, self.members_at_once)
        if not one:
            step = jax.shard_map(step, mesh=mesh, in_specs=(spec, spec), out_specs=(spec, spec), check_vma=False)
        if self.pbt:  # outside shard_map: a gather across the whole grid axis
            step = _with_pbt(step, config, self.grid_size)
        init = _pbt_init(trainer.init) if self.pbt else trainer.init
        # Compile options only apply where they were measured: CPU (`envs_mjx.cpu_compiler_options`).
        cpu = self.devices[0].platform == "cpu"
        self.compiler_options = cpu_compiler_options(env) if cpu else {}
        init_options = {**self.compiler_options, **CPU_INIT_OPTIONS} if cpu else None
        self._init = jax.jit(jax.vmap(init), in_shardings=self.sharding, out_shardings=self.sharding,
                             compiler_options=init_options)
        self._step = jax.jit(step, in_shardings=(self.sharding, self.sharding),
                             out_shardings=(self.sharding, self.sharding), donate_argnums=0,
                             compiler_options=self.compiler_options or None)

    def _pad(self, x) -> jax.Array:
        return jax.device_put(pad_grid(x, self.padded_size), self.sharding)

    def _init_args(self, seeds) -> tuple:
        return (self._pad(seeds), self._pad(self._eta)) if self.pbt else (self._pad(seeds),)

    def init(self, seeds) -> TrainState:
        """States for seeds int[G] (padded to the device count: leaves [G_padded, ...])."""
        return self._init(*self._init_args(seeds))

    def abstract_state(self, seeds) -> TrainState:
        """Shapes, dtypes and shardings of `init(seeds)`, without computing it (for restoring)."""
        shapes = jax.eval_shape(self._init, *self._init_args(seeds))
        return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=self.sharding), shapes)

    def train_step(self, state: TrainState, eta) -> tuple[TrainState, EpochMetrics]:
        """One epoch of every member: eta float32[G, N] (ignored under PBT: the members carry their own).
        Metrics keep only the real members."""
        state, metrics = self._step(state, self._pad(eta))
        return state, jax.tree.map(lambda x: x[: self.grid_size], metrics)


def _local_step(trainer: Trainer, local: int, members_at_once: int):
    """One epoch of a device's `local` members, `members_at_once` of them vmapped together at a time."""

    def step(state: TrainState, eta: jax.Array):
        if members_at_once == local:
            return jax.vmap(trainer.train_step)(state, eta)
        # Explicit shapes, not lax.map(batch_size=...): its reshape(-1) fails on zero-size leaves.
        k = members_at_once
        grouped = jax.tree.map(lambda x: x.reshape((local // k, k) + x.shape[1:]), (state, eta))
        out = jax.lax.map(lambda x: jax.vmap(trainer.train_step)(*x), grouped)
        return jax.tree.map(lambda x: x.reshape((local,) + x.shape[2:]), out)

    return step


def _pbt_init(init):
    """A member's `init(seed)` as `(seed, eta float32[N]) -> TrainState` with its PBT state (`pbt.init_member`)."""
    return lambda seed, eta: init(seed).replace(pbt=init_member(eta))


def _with_pbt(step, config: Config, grid_size: int):
    """The grid's epoch `step` followed by PBT's step across the grid axis (`pbt.pbt_step`), whose record the
    metrics carry."""

    def grid_step(state: TrainState, eta: jax.Array):
        state, metrics = step(state, eta)
        state, record = pbt_step(state, config, grid_size)
        return state, metrics._replace(pbt=record)

    return grid_step


def make_grid_train(config: Config, env: Env, devices: Sequence[jax.Device] | None = None,
                    members_at_once: int | None = None) -> GridTrainer:
    """The whole grid of `config` as one compiled program, sharded over `devices` (default: `grid_devices`)."""
    return GridTrainer(config, env, devices, members_at_once=members_at_once)
