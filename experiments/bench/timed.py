"""A compiled grid trainer whose epochs are timed, shared by the benchmarks that time whole epochs.

Compile time is measured apart: the first epoch compiles, and if it changes
any state leaf's type (which would make the second call compile again) that
second compile is named and kept out of the timed epochs too. `SameWork` and
`our_sac` are the settings and our side of the comparisons with other SAC
trainers (vs_brax.py, vs_rejax.py).
"""
from __future__ import annotations

import dataclasses
import os
import statistics
import time
from typing import Callable, Sequence
from unittest import mock

import jax
import jax.numpy as jnp
from brax.envs.base import Env

import ccp_jax.trainer as trainer_module
from ccp_jax.collect import make_evaluate
from ccp_jax.config import Config, make_config
from ccp_jax.envs import make_env
from ccp_jax.grid import make_grid_train
from envs_mjx import XLA_CPU_EMITTERS, XLA_CPU_FLAG
from envs_mjx.maze import Maze


def emitters_on_everywhere() -> None:
    """XLA's CPU fusion emitters on for every program of this process (XLA's default); call before JAX computes.

    Our trainer compiles the maze epoch with them on (`envs_mjx.cpu_compiler_options`) while importing
    `ccp_jax` turns them off process-wide for MJX, which would slow only the other side (brax, the
    reference) of a maze comparison.
    """
    flags = os.environ.get("XLA_FLAGS", "").replace(XLA_CPU_FLAG, "")
    os.environ["XLA_FLAGS"] = (flags + f" --{XLA_CPU_EMITTERS}=true").strip()


def no_eval(config, env, actor):
    """A stand-in for `make_evaluate` whose `evaluate` returns zeros shaped like the real one's metrics.

    Patched into `ccp_jax.trainer` to time an epoch without its evaluation (the real evaluation is only
    traced abstractly, for its output shapes; it is not part of the compiled program).
    """
    real = make_evaluate(config, env, actor)

    def evaluate(*args):
        return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(real, *args))
    return evaluate


def avals(tree) -> list[tuple]:
    """(path, shape, dtype, weak_type) of every leaf: what jit's cache keys on."""
    return [(jax.tree_util.keystr(p), x.shape, x.dtype, getattr(x, "weak_type", False))
            for p, x in jax.tree_util.tree_flatten_with_path(tree)[0]]


@dataclasses.dataclass
class Alternating:
    """The arguments of a script that times versions of one grid trainer in one process, epochs alternating."""

    rooms: int = 3
    seeds: int = 1
    """Grid size (members one at a time on CPU, the default)."""
    reps: int = 8
    """Timed epochs of each version."""

    def config(self) -> Config:
        """The yardstick's settings (docs/design.md#the-learning-yardstick): "small" preset, [64, 64], the paper's epoch, buffer 2e5 per agent."""
        return make_config("small", rooms=self.rooms, seeds=tuple(range(self.seeds)), buffer_size=200_000)


class TimedEpochs:
    """Times one compiled epoch per `epoch()` call; a subclass's `_step()` advances its state and returns what to wait for."""

    times: list[float]

    def _step(self):
        raise NotImplementedError

    def epoch(self) -> float:
        t = time.perf_counter()
        jax.block_until_ready(self._step())
        self.times.append(time.perf_counter() - t)
        return self.times[-1]

    @property
    def median(self) -> float:
        return statistics.median(self.times)


def alternate(runs: dict[str, TimedEpochs], reps: int) -> None:
    """`reps` rounds of one timed epoch of every run, the order reversed every round (a change of load on a shared
    machine then lands on all of them alike)."""
    for r in range(reps):
        for timed in (list(runs.values()) if r % 2 == 0 else list(runs.values())[::-1]):
            timed.epoch()


def paired_table(runs: dict[str, TimedEpochs], base: str, ratio_name: str,
                 ratio: Callable[[float, float], float]) -> str:
    """A Markdown table of each run's epoch seconds (median, min, max) and the median (min – max) over rounds of
    `ratio(base's epoch, this run's epoch)` (`ratio_name` heads that column)."""
    rows = ["| version | epoch s (median) | min | max | " + ratio_name + ", median of paired ratios (min – max) |",
            "|---|---|---|---|---|"]
    for name, timed in runs.items():
        ratios = [ratio(a, b) for a, b in zip(runs[base].times, timed.times)]
        rows.append(f"| {name} | {timed.median:.3f} | {min(timed.times):.2f} | {max(timed.times):.2f} | "
                    f"{statistics.median(ratios):.3f} ({min(ratios):.3f} – {max(ratios):.3f}) |")
    return "\n".join(rows)


class TimedGrid(TimedEpochs):
    """The grid trainer of `config`, built, compiled and warmed; `epoch()` runs and times one `train_step`.

    `devices`: where the grid trains (default: those `grid_devices` picks).

    `first`: the compiling epoch's seconds; `compile_s`: first minus a warm epoch; `retraced`: leaves
    whose type the first epoch changed (then `second` is the recompiling epoch's seconds).
    """

    def __init__(self, config: Config, env: Env | None = None, evaluate: bool = True,
                 members_at_once: int | None = None, devices: Sequence[jax.Device] | None = None):
        env = env or make_env(config)
        build = lambda: make_grid_train(config, env, devices, members_at_once=members_at_once)
        if evaluate:
            self.trainer = build()
        else:
            with mock.patch.object(trainer_module, "make_evaluate", no_eval):
                self.trainer = build()
        self.eta, seeds = (jnp.asarray(x) for x in config.grid_arrays())
        self.state = jax.block_until_ready(self.trainer.init(seeds))
        self.times: list[float] = []
        before = avals(self.state)
        self.first = self.epoch()
        self.retraced = [f"{a[0]}: {a[1:]} -> {b[1:]}" for a, b in zip(before, avals(self.state)) if a != b]
        self.second = self.epoch() if self.retraced else 0.0
        self.compile_s = self.first - self.epoch()
        self.times.clear()

    def _step(self):
        self.state, metrics = self.trainer.train_step(self.state, self.eta)
        return self.state, metrics


@dataclasses.dataclass
class SameWork:
    """End-to-end SAC on the maze as both sides of a comparison with another SAC trainer run it."""

    hidden: tuple[int, ...] = (64, 64)
    """Hidden layers of actor and each critic (both trainers)."""
    rooms: int = 2
    batch: int = 256
    num_envs: int = 5
    """Envs stepped together."""
    grad_updates_per_step: int = 1
    """Updates per step of num_envs envs: 1 with 5 envs is the paper's 0.2 updates per env step."""
    epoch_steps: int = 5000
    """Env steps per timed epoch (the paper's epoch: 5000)."""
    buffer: int = 100_000
    start_steps: int = 1000
    """Env steps before the first update (ours: uniform-random actions; the other trainer: its prefill)."""
    eval_episodes: int = 10
    episode_length: int = 1000
    roof: bool = True
    """Also measure the jnp.dot roof at the widest layer, for context."""


def updates_per_epoch(args: SameWork) -> int:
    if (args.epoch_steps * args.grad_updates_per_step) % args.num_envs or args.epoch_steps % args.num_envs:
        raise SystemExit("epoch_steps must be a multiple of num_envs")
    return args.epoch_steps * args.grad_updates_per_step // args.num_envs


def our_sac(args: SameWork, seeds: Sequence[int], evaluate: bool, members_at_once: int | None = None) -> TimedGrid:
    """Our grid trainer, one agent (`algo="sac"`), on `args`' work: one member per seed (`members_at_once`:
    as `make_grid_train`'s, default `devices.default_members_at_once`)."""
    config = make_config(
        "paper", rooms=args.rooms, algo="sac", hidden=args.hidden, batch_size=args.batch,
        num_envs=args.num_envs, steps_per_epoch=args.epoch_steps, train_loops_per_epoch=updates_per_epoch(args),
        total_steps=1000 * args.epoch_steps, buffer_size=args.buffer, start_steps=args.start_steps,
        eval_episodes=args.eval_episodes, max_episode_steps=args.episode_length, seeds=tuple(seeds))
    return TimedGrid(config, Maze(rooms=args.rooms, episode_length=args.episode_length), evaluate,
                     members_at_once=members_at_once)
