"""The trainer: `make_train(config, env)` returns pure `init` and `train_step` functions.

`train_step` is one epoch of one run — collect `steps_per_epoch` env steps,
run `train_loops_per_epoch` joint updates of all agents (in
`train_cycles_per_epoch` alternating rounds of collection and updates),
evaluate — and is a single jittable function (docs/design.md#the-trainer).
`grid.make_grid_train` maps both over the grid axis (seeds × ratios), so a
whole sweep is one compiled program.
"""
from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State
from flax import struct

from ccp_jax import buffer as replay
from ccp_jax import eta as ratios
from ccp_jax import health
from ccp_jax.buffer import ReplayBuffer
from ccp_jax.collect import EpisodeStats, EvalMetrics, TracedOnce, make_collect, make_evaluate, per_episode
from ccp_jax.config import Config
from ccp_jax.learner import (AgentState, Learner, Networks, UpdateMetrics, init_agents, make_learner, make_networks,
                             train_loops)
from ccp_jax.pbt import PbtMember, PbtRecord, accumulate


class TrainState(struct.PyTreeNode):
    """Everything a run carries between epochs (one grid member; the grid adds a leading axis)."""

    agents: AgentState
    buffer: ReplayBuffer
    env_state: State  # leaves [num_envs, ...]
    key: jax.Array
    env_steps: jax.Array  # int32[]
    epoch: jax.Array  # int32[]
    eta_auto: jax.Array  # float32[N]: the outcome rule's ratios for "auto" members (`eta.outcome_eta`)
    successor_succeeded: jax.Array  # bool[N]: a training episode has succeeded in stage n + 1 ("trusted")
    pbt: PbtMember | None = None  # with `pbt_every`: the member's ratios and window (None: the grid's ratios)


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
    frozen: jax.Array  # bool[]: the epoch's updates diverged and were discarded (`health.diverged`)
    pbt: PbtRecord | None = None  # with `pbt_every`: the grid's PBT step after the epoch (`grid.GridTrainer`)


class Trainer(NamedTuple):
    """One run's networks and its pure, jittable `init` and `train_step` (`make_train`)."""

    networks: Networks
    init: Callable[[jax.Array], TrainState]  # seed int32[] -> TrainState
    train_step: Callable[[TrainState, jax.Array], tuple[TrainState, EpochMetrics]]  # (state, eta[N])


def make_train(config: Config, env: Env) -> Trainer:
    """Pure `init(seed)` and `train_step(state, eta)` for one run of `config` on `env`."""
    config.check_trainable()
    if env.num_stages != config.num_stages:
        raise ValueError(f"rooms: the env has {env.num_stages} stages but the config expects {config.num_stages}")
    obs_size, action_size = env.observation_size, env.action_size
    env = TracedOnce(env)
    nets = make_networks(config, action_size)
    collect = make_collect(config, env, nets.actor)
    evaluate = make_evaluate(config, env, nets.actor)
    learner = make_learner(config, nets, action_size)

    def train_step(state: TrainState, eta: jax.Array) -> tuple[TrainState, EpochMetrics]:
        """One epoch: eta float32[N], NaN for "auto"; a member under PBT trains with its own ratios instead."""
        eta = ratios.epoch_eta(eta if state.pbt is None else state.pbt.eta, state.eta_auto, config)
        key, k_collect, k_train, k_eval = jax.random.split(state.key, 4)
        k_train, k_pulls = jax.random.split(k_train)
        agents, env_state, buffer, env_steps, stats, train_metrics = run_cycles(
            config, collect, learner, state, eta, k_collect, k_train)
        train_metrics = jax.tree.map(lambda x: x.mean(0), train_metrics)
        # A diverged epoch's updates are discarded: the member keeps its last healthy parameters (and optimiser
        # states) while the grid trains on; each later epoch tries again from them.
        frozen = health.diverged(train_metrics, agents, config.value_bound)
        agents = jax.tree.map(lambda old, new: jnp.where(frozen, old, new), state.agents, agents)
        pull_own, pull_next = learner.action_pulls(agents, replay.sample(buffer, k_pulls, config.sac.batch_size), eta,
                                                   k_pulls)
        metrics = EpochMetrics(env_steps=env_steps, eval=evaluate(agents.actor, k_eval), train=train_metrics,
                               frozen=frozen,
                               train_episodes=stats.episodes,
                               train_success=per_episode(stats.successes, stats.episodes),
                               train_stage_fraction=per_episode(stats.stages, stats.episodes),
                               buffer_size=buffer.size, pull_own=pull_own, pull_next=pull_next)
        passed = ratios.successor_succeeded(stats.stages, stats.successes, config.num_agents)
        succeeded = state.successor_succeeded | passed
        eta_auto = ratios.next_auto(state.eta_auto, succeeded, stats.stages, stats.successes, config)
        new_state = TrainState(agents=agents, buffer=buffer, env_state=env_state, key=key,
                               env_steps=env_steps, epoch=state.epoch + 1, eta_auto=eta_auto,
                               successor_succeeded=succeeded,
                               pbt=None if state.pbt is None else accumulate(state.pbt, stats))
        return new_state, metrics

    init = functools.partial(init_state, config, env, nets, obs_size, action_size)
    return Trainer(networks=nets, init=init, train_step=train_step)


def init_state(config: Config, env: Env, nets: Networks, obs_size: int, action_size: int,
               seed: jax.Array) -> TrainState:
    """A run's state before its first epoch, from seed int32[]."""
    key = jax.random.PRNGKey(seed)
    key, k_agents, k_env = jax.random.split(key, 3)
    agents = init_agents(nets, k_agents, config.num_agents, obs_size, action_size,
                         value_range=config.value_bound, initial_alpha=config.sac.initial_alpha)
    num_channels = 1 if config.num_agents == 1 else config.num_stages
    buffer = replay.init_buffer(replay.zero_transition(obs_size, action_size, num_channels),
                                config.num_agents, config.sac.buffer_size)
    env_state = jax.vmap(env.reset)(jax.random.split(k_env, config.budget.num_envs))
    return TrainState(agents=agents, buffer=buffer, env_state=env_state, key=key,
                      env_steps=jnp.int32(0), epoch=jnp.int32(0), eta_auto=ratios.initial_auto(config),
                      successor_succeeded=jnp.zeros((config.num_agents,), bool))


def run_cycles(config: Config, collect: Callable, learner: Learner, state: TrainState, eta: jax.Array,
               k_collect: jax.Array, k_train: jax.Array
               ) -> tuple[AgentState, State, ReplayBuffer, jax.Array, EpisodeStats, UpdateMetrics]:
    """The epoch's `train_cycles_per_epoch` rounds of collection, then updates.

    Returns (agents, env_state, buffer, env_steps, the epoch's collection stats summed over rounds,
    UpdateMetrics with leaves [train_loops_per_epoch, N]).
    """
    cycles = config.ablations.train_cycles_per_epoch
    # One cycle keeps the key stream of the single-collection epoch.
    per_cycle = (lambda k: k[None]) if cycles == 1 else (lambda k: jax.random.split(k, cycles))

    def cycle(carry, keys):
        agents, env_state, buffer, env_steps = carry
        k_collect, k_train = keys
        env_state, buffer, stats = collect(agents.actor, env_state, buffer, k_collect, env_steps)
        ready = replay.ready(buffer, config.sac.batch_size)
        agents, train_metrics = train_loops(learner, agents, buffer, eta, ready, k_train,
                                            config.budget.train_loops_per_epoch // cycles, config.sac.batch_size)
        env_steps = env_steps + config.budget.steps_per_epoch // cycles
        return (agents, env_state, buffer, env_steps), (stats, train_metrics)

    (agents, env_state, buffer, env_steps), (stats, train_metrics) = jax.lax.scan(
        cycle, (state.agents, state.env_state, state.buffer, state.env_steps),
        (per_cycle(k_collect), per_cycle(k_train)))
    stats = jax.tree.map(lambda x: x.sum(0), stats)
    train_metrics = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), train_metrics)
    return agents, env_state, buffer, env_steps, stats, train_metrics
