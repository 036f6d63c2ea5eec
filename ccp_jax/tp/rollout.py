"""Acting under TP: the env's stage is the meta-policy; primitive or transition policy acts.

Per env, the controller is in one of two modes. A primitive (frozen,
deterministic) acts while the stage is unfinished. When the stage advances
(not at an episode's start), the transition policy leading into the new
stage's primitive takes over; each step it either moves (a Gaussian action,
one env step) or terminates. On the step it terminates, the primitive acts
from that same state, so every loop iteration is exactly one env step and
`env_steps` counts primitive and transition steps alike. Termination is forced
after `tp_max_steps` transition steps, and a transition also ends when the
episode does or when its own steps complete the subtask.

The states a transition visited wait in a per-env pending segment until its
primitive's outcome is known (maybe epochs later): if that primitive then
completes its stage (or the task), they go to the success buffer with labels
δ^(T−t); if the episode ends first, to the failure buffer with label 0.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State
from flax import struct

from ccp_jax.collect import auto_reset, episode_metrics, policy_mean_and_log_std, stage_counts, where_done
from ccp_jax.config import Config
from ccp_jax.networks import deterministic_action
from ccp_jax.tp.networks import Proximity, RunningNorm, TransitionPolicy, Value, normalise
from ccp_jax.tp.ppo import Samples
from ccp_jax.tp.primitives import Primitives
from ccp_jax.tp.proximity import ProximityData, SegmentBuffer, buffer_add, buffer_init, proximity_targets


class TPNets(NamedTuple):
    """The flax modules and the frozen primitives the controller acts with."""

    policy: TransitionPolicy
    value: Value
    proximity: Proximity
    primitives: Primitives


class TPParams(NamedTuple):
    """What acting needs of the learnable state; leaves [K, ...] (K = N − 1 transition policies)."""

    policy: object
    proximity: object
    norm: RunningNorm


class Control(struct.PyTreeNode):
    """Per-env controller state, leaves [E, ...]."""

    in_transition: jax.Array  # bool[E]: a transition policy acts at the current state
    steps: jax.Array  # int32[E]: transition steps taken in the current segment
    pending_obs: jax.Array  # float32[E, L, o]: states of the last transition, awaiting its primitive's outcome
    pending_len: jax.Array  # int32[E]: states in pending_obs (0: nothing pending)
    pending_policy: jax.Array  # int32[E]: transition policy of the pending segment


def control_init(num_envs: int, max_len: int, obs_size: int) -> Control:
    zeros = jnp.zeros((num_envs,), jnp.int32)
    return Control(in_transition=jnp.zeros((num_envs,), bool), steps=zeros,
                   pending_obs=jnp.zeros((num_envs, max_len, obs_size)), pending_len=zeros, pending_policy=zeros)


def pick(stacked: jax.Array, k: jax.Array) -> jax.Array:
    """Row k[e] of stacked [K, E, ...] for each env: -> [E, ...]."""
    return jnp.take_along_axis(stacked, k.reshape((1, -1) + (1,) * (stacked.ndim - 2)), axis=0)[0]


def per_policy(apply: Callable, params, norm: RunningNorm, obs: jax.Array, k: jax.Array):
    """Every policy's `apply` on the env batch obs [E, o] (its own normaliser), row k[e] kept."""
    out = jax.vmap(lambda p, s: apply(p, normalise(s, obs)))(params, norm)
    return jax.tree.map(lambda x: pick(x, k), out)


def proximity_of(nets: TPNets, params: TPParams, obs: jax.Array, k: jax.Array) -> jax.Array:
    """P_k(s) clipped to [0, 1]: obs [E, o], k int32[E] -> [E]."""
    return jnp.clip(per_policy(nets.proximity.apply, params.proximity, params.norm, obs, k), 0.0, 1.0)


class Decision(NamedTuple):
    action: jax.Array  # float32[E, a]: what the env executes
    raw: jax.Array  # float32[E, a]: the transition policy's unclipped Gaussian sample
    term: jax.Array  # bool[E]: the transition terminates here (chosen or forced)
    forced: jax.Array  # bool[E]
    moving: jax.Array  # bool[E]: the transition policy's action is executed
    k: jax.Array  # int32[E]: transition policy of the current stage (leads into it)


def decide(config: Config, nets: TPNets, params: TPParams, state: State, in_transition: jax.Array,
           steps: jax.Array, key: jax.Array, deterministic: bool) -> Decision:
    """Who acts in each env and with what action (batched over E envs)."""
    stage = state.info["stage"]
    k = jnp.clip(stage - 1, 0, config.num_stages - 2)
    mean, log_std, logits = per_policy(nets.policy.apply, params.policy, params.norm, state.obs, k)
    k_act, k_term = jax.random.split(key)
    if deterministic:
        raw, chosen = mean, jnp.argmax(logits, -1) == 1
    else:
        raw = mean + jnp.exp(log_std) * jax.random.normal(k_act, mean.shape)
        chosen = jax.random.categorical(k_term, logits) == 1
    forced = in_transition & (steps >= config.tp.tp_max_steps)
    term = in_transition & (chosen | forced)
    moving = in_transition & ~term
    prim = nets.primitives
    prim_mean, _ = policy_mean_and_log_std(prim.actor, prim.params, state.obs, stage)
    action = jnp.where(moving[:, None], jnp.clip(raw, -1.0, 1.0), deterministic_action(prim_mean))
    return Decision(action=action, raw=raw, term=term, forced=forced, moving=moving, k=k)


def next_mode(d: Decision, steps: jax.Array, advanced: jax.Array, done: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(in_transition, steps) after the env step: a transition starts whenever the stage advances."""
    in_transition = ~done & (d.moving | advanced)
    steps = jnp.where(d.moving & ~advanced & ~done, steps + 1, 0)
    return in_transition, steps


class RolloutStats(NamedTuple):
    """Counts summed over an epoch's rollout; per transition policy [K] unless noted."""

    samples: jax.Array  # transition samples (steps at which a transition policy acted)
    handovers: jax.Array  # segments that ended by (chosen or forced) termination
    forced: jax.Array  # of which forced by the step limit
    won: jax.Array  # segments labelled success (the primitive after them completed its stage)
    lost: jax.Array  # segments labelled failure
    episodes: jax.Array  # float32[]: training episodes ended
    successes: jax.Array  # float32[]: of which successful
    stages: jax.Array  # float32[N]: of which reached stage n


def make_rollout(config: Config, env: Env, nets: TPNets) -> Callable:
    """`rollout(params, env_state, control, data, key) -> (env_state, control, data, samples [T, E], stats)`.

    `config.collect_iters` vectorised steps over `config.budget.num_envs` envs with the
    stochastic transition policies; rewards use the current predictors.
    """
    num_envs, num_k, max_len = config.budget.num_envs, config.num_stages - 1, config.tp.tp_max_steps + 1
    v_step = jax.vmap(env.step)

    def one_step(params: TPParams, carry, key):
        env_state, ctrl, data, stats = carry
        k_act, k_reset = jax.random.split(key)
        d = decide(config, nets, params, env_state, ctrl.in_transition, ctrl.steps, k_act, deterministic=False)
        nxt = v_step(env_state, d.action)
        done, success = nxt.done > 0, nxt.metrics["success"] > 0
        stage, next_stage = env_state.info["stage"], nxt.info["stage"]
        advanced = next_stage > stage
        in_tp = ctrl.in_transition

        # Reward: proximity increase while moving; the segment's last sample adds the terminal proximity
        # (1 when the transition's own steps completed the subtask: such a state is in no primitive's way).
        p_now, p_next = proximity_of(nets, params, env_state.obs, d.k), proximity_of(nets, params, nxt.obs, d.k)
        completed = d.moving & (advanced | success)
        seg_end = in_tp & (d.term | done | completed)
        reward = jnp.where(d.term, p_now, p_next - p_now + jnp.where(seg_end, jnp.where(completed, 1.0, p_next), 0.0))
        f = lambda x: x.astype(jnp.float32)
        sample = Samples(obs=env_state.obs, policy=d.k, action=d.raw, term=f(d.term), forced=f(d.forced),
                         reward=reward * in_tp, end=f(seg_end), valid=f(in_tp))

        # Pending segment: append the state, then label it once its primitive's outcome is known.
        pending_policy = jnp.where(in_tp & (ctrl.pending_len == 0), d.k, ctrl.pending_policy)
        row = jnp.where(in_tp, ctrl.pending_len, max_len)  # out of bounds: dropped
        pending_obs = ctrl.pending_obs.at[jnp.arange(num_envs), row].set(env_state.obs, mode="drop")
        pending_len = ctrl.pending_len + in_tp
        has = pending_len > 0
        won = has & ((next_stage > pending_policy + 1) | success)
        lost = has & done & ~won
        labels = proximity_targets(pending_len, won, max_len, config.tp.tp_delta)
        data = ProximityData(
            success=buffer_add(data.success, pending_obs, labels, pending_policy, jnp.where(won, pending_len, 0)),
            failure=buffer_add(data.failure, pending_obs, labels, pending_policy, jnp.where(lost, pending_len, 0)),
            permanent=data.permanent)
        in_transition, steps = next_mode(d, ctrl.steps, advanced, done)
        ctrl = Control(in_transition=in_transition, steps=steps, pending_obs=pending_obs,
                       pending_len=jnp.where(won | lost, 0, pending_len), pending_policy=pending_policy)

        count = lambda mask, k: (mask[:, None] * (k[:, None] == jnp.arange(num_k))).sum(0).astype(jnp.float32)
        stats = RolloutStats(samples=stats.samples + count(in_tp, d.k),
                             handovers=stats.handovers + count(d.term, d.k),
                             forced=stats.forced + count(d.forced, d.k),
                             won=stats.won + count(won, pending_policy), lost=stats.lost + count(lost, pending_policy),
                             episodes=stats.episodes + done.sum(), successes=stats.successes + (done & success).sum(),
                             stages=stats.stages + stage_counts(done, next_stage, config.num_stages))
        env_state = auto_reset(env, nxt, k_reset)
        return (env_state, ctrl, data, stats), sample

    def rollout(params: TPParams, env_state: State, ctrl: Control, data: ProximityData, key: jax.Array):
        zk, z = jnp.zeros((num_k,)), jnp.zeros(())
        stats = RolloutStats(zk, zk, zk, zk, zk, z, z, jnp.zeros((config.num_stages,)))
        (env_state, ctrl, data, stats), samples = jax.lax.scan(
            lambda c, k: one_step(params, c, k), (env_state, ctrl, data, stats),
            jax.random.split(key, config.collect_iters))
        return env_state, ctrl, data, samples, stats

    return rollout


def make_evaluate(config: Config, env: Env, nets: TPNets) -> Callable:
    """`evaluate(params, key) -> (EvalMetrics, transition fraction)` over `config.budget.eval_episodes` deterministic
    episodes.

    Deterministic primitives, mean transition actions, terminate when the head
    prefers it. The second output is the fraction of env steps a transition
    policy took.
    """
    episodes, num_stages = config.budget.eval_episodes, config.num_stages
    v_step, v_reset = jax.vmap(env.step), jax.vmap(env.reset)

    def evaluate(params: TPParams, key: jax.Array):
        state = v_reset(jax.random.split(key, episodes))
        zeros = jnp.zeros((episodes,), jnp.float32)
        mode = (jnp.zeros((episodes,), bool), jnp.zeros((episodes,), jnp.int32))

        def cond(carry):
            return jnp.any(carry[0].done == 0) & (carry[-1] < config.task.max_episode_steps)

        def body(carry):
            state, (in_tp, steps), ret, length, moved, t = carry
            d = decide(config, nets, params, state, in_tp, steps, key, deterministic=True)
            nxt = v_step(state, d.action)
            mode = next_mode(d, steps, nxt.info["stage"] > state.info["stage"], nxt.done > 0)
            live = 1.0 - state.done
            return (where_done(state.done, state, nxt), mode, ret + live * nxt.reward, length + live,
                    moved + live * d.moving, t + 1)

        carry = (state, mode, zeros, zeros, zeros, jnp.int32(0))
        state, _, ret, length, moved, _ = jax.lax.while_loop(cond, body, carry)
        return episode_metrics(state, ret, length, num_stages), moved.sum() / jnp.maximum(length.sum(), 1.0)

    return evaluate


def make_initial_successes(config: Config, env: Env, primitives: Primitives) -> Callable:
    """`initial(key) -> (permanent SegmentBuffer, env steps)`: the predictors' permanent success states.

    Runs `tp_init_episodes` deterministic episodes of the primitives alone
    (no transitions). For every stage k ≥ 1 that its primitive completed, the
    first `tp_init_fraction` of the states it visited in that stage are
    stored for predictor k − 1 with label 1. One pass records every state
    (obs [T, E, o], T = max_episode_steps: 16 MB for 100 peg episodes) and
    each stage's extent and outcome; which states to keep is known only once
    a stage has ended, so they are stored afterwards, step by step as if
    during the pass. (Two passes that held no trajectory doubled the env
    steps, 200 k MJX steps per peg member, and two differently compiled MJX
    loops can drift apart: README, TP section.)
    """
    episodes, num_stages = config.tp.tp_init_episodes, config.num_stages
    v_step, v_reset = jax.vmap(env.step), jax.vmap(env.reset)
    big = jnp.iinfo(jnp.int32).max

    def initial(key: jax.Array) -> tuple[SegmentBuffer, jax.Array]:
        horizon = config.task.max_episode_steps
        trace = (jnp.zeros((horizon, episodes, env.observation_size)), jnp.zeros((horizon, episodes), jnp.int32),
                 jnp.zeros((horizon, episodes), bool))  # obs, stage and liveness of every state

        def cond(carry):
            return jnp.any(carry[0].done == 0) & (carry[-1] < horizon)

        def body(carry):
            state, (obs, stages, lives), t = carry
            live, stage = state.done == 0, state.info["stage"]
            trace = obs.at[t].set(state.obs), stages.at[t].set(stage), lives.at[t].set(live)
            mean, _ = policy_mean_and_log_std(primitives.actor, primitives.params, state.obs, stage)
            nxt = v_step(state, deterministic_action(mean))
            return where_done(state.done, state, nxt), trace, t + 1

        state = v_reset(jax.random.split(key, episodes))
        final, trace, _ = jax.lax.while_loop(cond, body, (state, trace, jnp.int32(0)))
        _, stages, lives = trace
        here = lives[..., None] & (stages[..., None] == jnp.arange(num_stages))  # [T, E, N]: live in stage n at t
        start = jnp.where(here.any(0), jnp.argmax(here, 0), big)  # first step in each stage (big: never)
        last = horizon - 1 - jnp.argmax(here[::-1], 0)
        done_stage = (final.info["stage"][:, None] > jnp.arange(num_stages)) | (final.metrics["success"][:, None] > 0)
        keep = jnp.where(done_stage, jnp.ceil(config.tp.tp_init_fraction * (last - start + 1)), 0).astype(jnp.int32)

        def store(buf, step):
            t, obs_t, stage, live = step
            rank = t - jnp.take_along_axis(start, stage[:, None], 1)[:, 0]
            take = live & (stage >= 1) & (rank < jnp.take_along_axis(keep, stage[:, None], 1)[:, 0])
            return buffer_add(buf, obs_t[:, None], jnp.ones((episodes, 1)), jnp.maximum(stage - 1, 0),
                              take.astype(jnp.int32)), None

        empty = buffer_init(num_stages - 1, config.tp.tp_buffer_size, env.observation_size)
        permanent, _ = jax.lax.scan(store, empty, (jnp.arange(horizon),) + trace)
        return permanent, lives.sum()

    return initial
