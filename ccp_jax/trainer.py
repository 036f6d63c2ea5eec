"""The trainer: `make_train(config, env)` returns pure `init` and `train_step` functions.

`train_step` is one epoch of one run — collect `steps_per_epoch` env steps,
run `train_loops_per_epoch` joint updates of all agents (in
`train_cycles_per_epoch` alternating rounds of collection and updates),
evaluate — and is a single jittable function. `make_grid_train` maps both over the grid axis
(seeds × ratios), so a whole sweep is one compiled program.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec, SingleDeviceSharding

from ccp_jax import buffer as replay
from ccp_jax.buffer import ReplayBuffer
from ccp_jax.collect import EvalMetrics, TracedOnce, make_collect, make_evaluate, per_episode
from ccp_jax.config import GATED_RULES, OUTCOME_RULES, Config, ConfigError, EtaAutoRule
from ccp_jax.devices import available_cores, grid_devices, pad_grid
from ccp_jax.learner import (AgentState, Networks, UpdateMetrics, critic_slots, init_agents, make_learner,
                             make_networks, train_loops)
from envs_mjx import cpu_compiler_options


class TrainState(struct.PyTreeNode):
    """Everything a run carries between epochs (one grid member; the grid adds a leading axis)."""

    agents: AgentState
    buffer: ReplayBuffer
    env_state: State  # leaves [num_envs, ...]
    key: jax.Array
    env_steps: jax.Array  # int32[]
    epoch: jax.Array  # int32[]
    eta_auto: jax.Array  # float32[N]: the outcome rules' ratios for "auto" members (`outcome_eta`)
    successor_succeeded: jax.Array  # bool[N]: a training episode has succeeded in stage n + 1 ("gated", "trusted")


class EpochMetrics(NamedTuple):
    """What one epoch reports. Per-agent fields are [N] (means over the epoch's updates)."""

    env_steps: jax.Array
    eval: EvalMetrics
    train: UpdateMetrics
    train_episodes: jax.Array
    train_success: jax.Array
    train_stage_fraction: jax.Array  # float32[N]: of the epoch's ended training episodes, the fraction reaching stage n
    buffer_size: jax.Array  # int32[N]
    pull_own: jax.Array  # float32[N]: mean ‖∂(η Q̂_n)/∂a‖ on one batch after the epoch's updates
    pull_next: jax.Array  # float32[N]: mean ‖∂((1 − η) Q̂_{n+1})/∂a‖


class Trainer(NamedTuple):
    networks: Networks
    init: Callable[[jax.Array], TrainState]  # seed int32[] -> TrainState
    train_step: Callable[[TrainState, jax.Array], tuple[TrainState, EpochMetrics]]  # (state, eta[N])


def _reached(stages: jax.Array, successes: jax.Array) -> jax.Array:
    """float32[N + 1]: episodes that reached each stage, then those that succeeded ("stage N")."""
    return jnp.concatenate([stages, successes[None]])


def successor_succeeded(stages: jax.Array, successes: jax.Array) -> jax.Array:
    """bool[N]: whether any of the epoch's episodes succeeded in stage n + 1 (reached stage n + 2, or the
    goal); False for the last agent, which has no successor. Arguments as `outcome_eta`'s."""
    beyond_next = _reached(stages, successes)[2:]
    return jnp.concatenate([beyond_next > 0, jnp.zeros((1,), bool)])


def outcome_eta(eta: jax.Array, stages: jax.Array, successes: jax.Array, rate: float,
                bounds: tuple[float, float], up_rate: float | None = None,
                rule: EtaAutoRule = "outcomes", gate: jax.Array | None = None, floor_step: float = 0.0) -> jax.Array:
    """One epoch's move of `--eta auto`'s outcome rules (`rule`): eta float32[N] -> float32[N].

    stages float32[N]: how many of the epoch's ended training episodes reached each stage; successes
    float32[]: how many succeeded. Of the episodes that entered stage n, those that failed in it push η_n
    up by `up_rate` (default `rate`) each (the agent's own subtask is the bottleneck: weigh its own
    critic more) and those that failed in stage n + 1 push it down by `rate` (it hands over where its
    successor fails: weigh the next critic more), as fractions of the episodes that entered stage n;
    clipped to `bounds`. An agent whose stage no episode entered keeps its η. (The last agent's entry
    moves too but is never used.) With `floor_step`, agent n's lower bound is bounds[0] + n × floor_step,
    never above the middle of `bounds`: a ramp of floors along the chain (the first agent's is bounds[0]).

    The "gated" rule needs `gate` bool[N] (`successor_succeeded`, accumulated over epochs): where it is
    False only the upward term applies, where True only the downward one. Until its successor has
    succeeded once, failures after a handover say that stage n + 1 is not learnt yet, not that the
    handover is bad (peg's insertions at the CPU budget).

    The "trusted" rule (also given `gate`) keeps both terms while the gate is False but holds η_n at or
    above the middle of `bounds`: a successor that has never succeeded is not weighed above the agent's
    own critic, and an agent that passes its own stage every time drifts back to even weighting instead of
    staying where its early failures pushed it (4 rooms: the third agent at 0.95, Naive's greedy door).
    Once the gate is True, only the downward term, down to the agent's lower bound.
    """
    reached = _reached(stages, successes)
    entered, failed = reached[:-1], reached[:-1] - reached[1:]
    failed_next = jnp.concatenate([failed[1:], jnp.zeros((1,), failed.dtype)])
    up_rate = rate if up_rate is None else up_rate
    middle = sum(bounds) / 2
    lower = jnp.minimum(bounds[0] + floor_step * jnp.arange(eta.shape[0]), middle)
    if rule in GATED_RULES:
        if gate is None:
            raise ValueError(f"outcome_eta: rule {rule!r} needs gate (successor_succeeded)")
        failed = jnp.where(gate, 0.0, failed)
        if rule == "trusted":
            lower = jnp.where(gate, lower, middle)
        else:
            failed_next = jnp.where(gate, failed_next, 0.0)
    moved = eta + (up_rate * failed - rate * failed_next) / jnp.maximum(entered, 1.0)
    return jnp.clip(jnp.where(entered > 0, moved, eta), lower, bounds[1])


def make_train(config: Config, env: Env) -> Trainer:
    """Pure `init(seed)` and `train_step(state, eta)` for one run of `config` on `env`."""
    if env.num_stages != config.num_stages:
        raise ValueError(f"rooms: the env has {env.num_stages} stages but the config expects {config.num_stages}")
    obs_size, action_size = env.observation_size, env.action_size
    env = TracedOnce(env)
    nets = make_networks(config, action_size)
    collect = make_collect(config, env, nets.actor)
    evaluate = make_evaluate(config, env, nets.actor)
    learner = make_learner(config, nets, action_size)
    num_channels = 1 if config.num_agents == 1 else config.num_stages
    capacity = config.buffer_size
    outcomes = config.eta_auto_rule in OUTCOME_RULES

    def init(seed: jax.Array) -> TrainState:
        key = jax.random.PRNGKey(seed)
        key, k_agents, k_env = jax.random.split(key, 3)
        agents = init_agents(nets, k_agents, config.num_agents, obs_size, action_size,
                             value_range=config.value_bound, initial_alpha=config.initial_alpha)
        buffer = replay.init_buffer(replay.zero_transition(obs_size, action_size, num_channels),
                                    config.num_agents, capacity)
        env_state = jax.vmap(env.reset)(jax.random.split(k_env, config.num_envs))
        eta_auto = jnp.full((config.num_agents,), sum(config.eta_auto_range) / 2, jnp.float32)
        return TrainState(agents=agents, buffer=buffer, env_state=env_state, key=key,
                          env_steps=jnp.int32(0), epoch=jnp.int32(0), eta_auto=eta_auto,
                          successor_succeeded=jnp.zeros((config.num_agents,), bool))

    def train_step(state: TrainState, eta: jax.Array) -> tuple[TrainState, EpochMetrics]:
        if outcomes:  # "auto" members train the epoch at the rule's ratios; the learner sees numbers
            eta = jnp.where(jnp.isnan(eta), state.eta_auto, eta)
        key, k_collect, k_train, k_eval = jax.random.split(state.key, 4)
        k_train, k_pulls = jax.random.split(k_train)
        cycles = config.train_cycles_per_epoch
        # One cycle keeps the key stream of the single-collection epoch.
        per_cycle = (lambda k: k[None]) if cycles == 1 else (lambda k: jax.random.split(k, cycles))

        def cycle(carry, keys):
            agents, env_state, buffer, env_steps = carry
            k_collect, k_train = keys
            env_state, buffer, stats = collect(agents.actor, env_state, buffer, k_collect, env_steps)
            ready = replay.ready(buffer, config.batch_size)

            agents, train_metrics = train_loops(learner, agents, buffer, eta, ready, k_train,
                                                config.train_loops_per_epoch // cycles, config.batch_size)
            env_steps = env_steps + config.steps_per_epoch // cycles
            return (agents, env_state, buffer, env_steps), (stats, train_metrics)

        (agents, env_state, buffer, env_steps), (stats, train_metrics) = jax.lax.scan(
            cycle, (state.agents, state.env_state, state.buffer, state.env_steps),
            (per_cycle(k_collect), per_cycle(k_train)))
        stats = jax.tree.map(lambda x: x.sum(0), stats)
        train_metrics = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), train_metrics)
        pull_own, pull_next = learner.action_pulls(agents, replay.sample(buffer, k_pulls, config.batch_size), eta,
                                                   k_pulls)
        eval_metrics = evaluate(agents.actor, k_eval)
        metrics = EpochMetrics(env_steps=env_steps, eval=eval_metrics,
                               train=jax.tree.map(lambda x: x.mean(0), train_metrics),
                               train_episodes=stats.episodes,
                               train_success=per_episode(stats.successes, stats.episodes),
                               train_stage_fraction=per_episode(stats.stages, stats.episodes),
                               buffer_size=buffer.size, pull_own=pull_own, pull_next=pull_next)
        succeeded = state.successor_succeeded | successor_succeeded(stats.stages, stats.successes)
        eta_auto = (outcome_eta(state.eta_auto, stats.stages, stats.successes, config.eta_auto_rate,
                                config.eta_auto_range, config.eta_auto_up_rate, config.eta_auto_rule, succeeded,
                                config.eta_auto_floor_step)
                    if outcomes else state.eta_auto)
        new_state = TrainState(agents=agents, buffer=buffer, env_state=env_state, key=key,
                               env_steps=env_steps, epoch=state.epoch + 1, eta_auto=eta_auto,
                               successor_succeeded=succeeded)
        return new_state, metrics

    return Trainer(networks=nets, init=init, train_step=train_step)


def check_members_at_once(members_at_once: int | None) -> None:
    """Refuses a group size below 1 (None means the default), naming the field."""
    if members_at_once is not None and members_at_once < 1:
        raise ConfigError("members_at_once", f"must be >= 1, got {members_at_once}")


# The init runs once; on a CPU its program (mostly the networks' random initialisers, vmapped) compiles 2-5x
# faster at LLVM's O1 (experiments/bench/init_compile.py): the same bits on the maze, MJX's reset by ulps.
CPU_INIT_OPTIONS = {"xla_backend_optimization_level": 1}


# On a CPU, how many floats one layer's stacked critic activations of a device's vmapped members may
# take (members × critic slots × batch × widest layer): 12 slots of SPEC §7's [64, 64] at batch 256,
# ≈ 0.75 MB. Measured on the 2-core CPU (experiments/bench/README.md, "Members vmapped on a CPU").
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
    if devices[0].platform != "cpu":
        return local_members
    if cores_per_device is None:
        cores_per_device = available_cores() / len(jax.local_devices(backend="cpu"))
    if cores_per_device < 2:
        return 1
    per_member = critic_slots(config) * config.batch_size * max(config.hidden)
    return max(1, CPU_VMAP_FLOATS // per_member)


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
    """

    def __init__(self, config: Config, env: Env, devices: Sequence[jax.Device] | None = None,
                 trainer: Trainer | None = None, members_at_once: int | None = None):
        trainer = make_train(config, env) if trainer is None else trainer  # e.g. TP brings its own
        self.networks = trainer.networks
        self.devices = list(devices) if devices else grid_devices(config.grid_size)
        self.grid_size = config.grid_size
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

        def local_step(state: TrainState, eta: jax.Array):
            if self.members_at_once == local:
                return jax.vmap(trainer.train_step)(state, eta)
            # Explicit shapes, not lax.map(batch_size=...): its reshape(-1) fails on zero-size leaves.
            k = self.members_at_once
            grouped = jax.tree.map(lambda x: x.reshape((local // k, k) + x.shape[1:]), (state, eta))
            out = jax.lax.map(lambda x: jax.vmap(trainer.train_step)(*x), grouped)
            return jax.tree.map(lambda x: x.reshape((local,) + x.shape[2:]), out)

        step = local_step if one else jax.shard_map(
            local_step, mesh=mesh, in_specs=(spec, spec), out_specs=(spec, spec), check_vma=False)
        # Compile options only apply where they were measured: CPU (`envs_mjx.cpu_compiler_options`).
        cpu = self.devices[0].platform == "cpu"
        self.compiler_options = cpu_compiler_options(env) if cpu else {}
        init_options = {**self.compiler_options, **CPU_INIT_OPTIONS} if cpu else None
        self._init = jax.jit(jax.vmap(trainer.init), in_shardings=self.sharding, out_shardings=self.sharding,
                             compiler_options=init_options)
        self._step = jax.jit(step, in_shardings=(self.sharding, self.sharding),
                             out_shardings=(self.sharding, self.sharding), donate_argnums=0,
                             compiler_options=self.compiler_options or None)

    def _pad(self, x) -> jax.Array:
        return jax.device_put(pad_grid(x, self.padded_size), self.sharding)

    def init(self, seeds) -> TrainState:
        """States for seeds int[G] (padded to the device count: leaves [G_padded, ...])."""
        return self._init(self._pad(seeds))

    def abstract_state(self, seeds) -> TrainState:
        """Shapes, dtypes and shardings of `init(seeds)`, without computing it (for restoring)."""
        shapes = jax.eval_shape(self._init, self._pad(seeds))
        return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=self.sharding), shapes)

    def train_step(self, state: TrainState, eta) -> tuple[TrainState, EpochMetrics]:
        """One epoch of every member: eta float32[G, N]. Metrics keep only the real members."""
        state, metrics = self._step(state, self._pad(eta))
        return state, jax.tree.map(lambda x: x[: self.grid_size], metrics)


def make_grid_train(config: Config, env: Env, devices: Sequence[jax.Device] | None = None,
                    members_at_once: int | None = None) -> GridTrainer:
    """The whole grid of `config` as one compiled program, sharded over `devices` (default: `grid_devices`)."""
    return GridTrainer(config, env, devices, members_at_once=members_at_once)
