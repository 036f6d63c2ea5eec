"""`make_tp_train(config, env, primitives)`: init / train_step of one TP run, shaped like `ccp_jax.trainer`.

`train_step` is one epoch, one jittable function: roll out `steps_per_epoch`
env steps (primitive and transition steps alike) → update the observation
normalisers → GAE over transition steps → `tp_prox_updates` predictor steps
→ PPO epochs of every transition policy → deterministic evaluation. The K =
N − 1 transition policies (and predictors) are a stacked axis; `GridTrainer`
vmaps the whole step over seeds, so a TP grid is one compiled program.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.envs.base import Env, State
from flax import struct

from ccp_jax.collect import EvalMetrics, TracedOnce, per_episode
from ccp_jax.config import Config
from ccp_jax.grid import GridTrainer
from ccp_jax.trainer import Trainer
from ccp_jax.tp.networks import (Proximity, RunningNorm, TransitionPolicy, Value, norm_init, norm_update,
                                 normalise)
from ccp_jax.tp.ppo import PPOMetrics, gae, log_prob, make_ppo_update
from ccp_jax.tp.primitives import Primitives, load_primitives
from ccp_jax.tp.proximity import (PredictorMetrics, ProximityData, buffer_init, clip_each_by_norm,
                                  make_predictor_update)
from ccp_jax.tp.rollout import (Control, RolloutStats, TPNets, TPParams, control_init, make_evaluate,
                                make_initial_successes, make_rollout, per_policy)

PROX_GRAD_CLIP = 10.0  # per-variable gradient-norm clip of the predictors (released code)
PROX_BETA1 = 0.5


class TransitionAgents(struct.PyTreeNode):
    """The learned transition policies, leaves [K, ...]. (`actor` is the name checkpoints save as the policy.)"""

    actor: Any  # TransitionPolicy params
    value: Any
    opt: optax.OptState
    norm: RunningNorm  # running observation moments of each policy's states (policy, value and predictor inputs)


class Predictors(struct.PyTreeNode):
    params: Any  # Proximity params [K, ...]
    opt: optax.OptState
    data: ProximityData


class TPState(struct.PyTreeNode):
    """Everything a TP run carries between epochs (one grid member)."""

    agents: TransitionAgents
    predictors: Predictors
    env_state: State  # leaves [num_envs, ...]
    control: Control
    key: jax.Array
    env_steps: jax.Array  # int32[]: env steps of TP training (primitive + transition)
    init_env_steps: jax.Array  # int32[]: env steps spent collecting the permanent success states
    epoch: jax.Array


class TPTrainMetrics(NamedTuple):
    """Per transition policy [K]."""

    rollout: RolloutStats
    predictor: PredictorMetrics  # means over the epoch's predictor steps
    ppo: PPOMetrics
    success_buffer: jax.Array  # int32[K] fill of the online success / failure / permanent buffers
    failure_buffer: jax.Array
    permanent_buffer: jax.Array


class TPEpochMetrics(NamedTuple):
    env_steps: jax.Array
    eval: EvalMetrics
    train_episodes: jax.Array
    train_success: jax.Array
    train_stage_fraction: jax.Array  # float32[N]
    eval_transition_fraction: jax.Array  # fraction of evaluation env steps taken by transition policies
    init_env_steps: jax.Array
    tp: TPTrainMetrics


def init_state(config: Config, env: Env, nets: TPNets, ppo_tx, prox_tx, initial: Callable, seed: jax.Array) -> TPState:
    """A TP run's first state: K = N − 1 transition policies, values and proximity predictors, the permanent
    success states from the primitives' own episodes, and the envs reset."""
    obs_size, num_k = env.observation_size, config.num_stages - 1
    key = jax.random.PRNGKey(seed)
    key, k_pi, k_v, k_p, k_env, k_init = jax.random.split(key, 6)
    dummy = jnp.zeros((obs_size,))
    actor = jax.vmap(lambda k: nets.policy.init(k, dummy))(jax.random.split(k_pi, num_k))
    value = jax.vmap(lambda k: nets.value.init(k, dummy))(jax.random.split(k_v, num_k))
    prox = jax.vmap(lambda k: nets.proximity.init(k, dummy))(jax.random.split(k_p, num_k))
    permanent, init_steps = initial(k_init)
    # The normalisers start from the permanent success states, the only states known before training.
    valid = jnp.arange(config.tp.tp_buffer_size)[None, :] < permanent.size[:, None]
    norm = jax.vmap(norm_update, in_axes=(None, 0, 0))(norm_init(obs_size), permanent.obs,
                                                        valid.astype(jnp.float32))
    empty = buffer_init(num_k, config.tp.tp_buffer_size, obs_size)
    agents = TransitionAgents(actor=actor, value=value, opt=jax.vmap(ppo_tx.init)((actor, value)), norm=norm)
    predictors = Predictors(params=prox, opt=jax.vmap(prox_tx.init)(prox),
                            data=ProximityData(success=empty, failure=empty, permanent=permanent))
    env_state = jax.vmap(env.reset)(jax.random.split(k_env, config.budget.num_envs))
    return TPState(agents=agents, predictors=predictors, env_state=env_state,
                   control=control_init(config.budget.num_envs, config.tp.tp_max_steps + 1, obs_size), key=key,
                   env_steps=jnp.int32(0), init_env_steps=init_steps, epoch=jnp.int32(0))



def ppo_inputs(config: Config, nets: TPNets, agents: TransitionAgents, samples, env_state: State, control: Control):
    """The rollout's transition samples, flattened to [M = T·E], made ready for PPO.

    The normalisers first take in this epoch's transition states; values
    and old log-probabilities are then computed with the new moments, so
    PPO's ratios start at exactly 1. Returns (norm [K], samples [M],
    weight [K, M] = each policy's own samples, logp_old, adv, ret [M]).
    """
    num_k = config.num_stages - 1
    flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), samples)
    mine = ((flat.policy[None, :] == jnp.arange(num_k)[:, None]) * flat.valid).astype(jnp.float32)
    norm = jax.vmap(norm_update, in_axes=(0, None, 0))(agents.norm, flat.obs, mine)

    def heads(pi, v, stats):
        obs = normalise(stats, flat.obs)
        mean, log_std, logits = nets.policy.apply(pi, obs)
        return log_prob(mean, log_std, logits, flat.action, flat.term, flat.forced), nets.value.apply(v, obs)

    logp_k, value_k = jax.vmap(heads)(agents.actor, agents.value, norm)  # [K, M]
    own = lambda x: jnp.take_along_axis(x, flat.policy[None], 0)[0]  # each sample's own policy
    logp_old, value = own(logp_k), own(value_k)
    # A segment still running when the rollout ends bootstraps from the value of the final state.
    last_k = jnp.clip(env_state.info["stage"] - 1, 0, num_k - 1)
    last_value = per_policy(nets.value.apply, agents.value, norm, env_state.obs, last_k) * control.in_transition
    adv, ret = gae(samples.reward, value.reshape(samples.valid.shape), samples.end, samples.valid, last_value,
                   config.tp.tp_gamma, config.tp.tp_gae_lambda)
    return norm, flat, mine, logp_old, adv.reshape(-1), ret.reshape(-1)



def make_tp_train(config: Config, env: Env, primitives: Primitives) -> Trainer:
    """Pure `init(seed)` and `train_step(state, eta)` (eta is ignored: TP has no ratio) for one TP run."""
    if env.num_stages != config.num_stages:
        raise ValueError(f"rooms: the env has {env.num_stages} stages but the config expects {config.num_stages}")
    action_size, num_k = env.action_size, config.num_stages - 1
    env = TracedOnce(env)  # reset and step are called in init, rollouts and evaluation: trace each once
    nets = TPNets(policy=TransitionPolicy(config.tp.tp_hidden, action_size), value=Value(config.tp.tp_hidden),
                  proximity=Proximity(config.tp.tp_prox_hidden), primitives=primitives)
    ppo_tx = optax.adam(config.tp.tp_lr)
    prox_tx = optax.chain(clip_each_by_norm(PROX_GRAD_CLIP), optax.adam(config.tp.tp_prox_lr, b1=PROX_BETA1))
    rollout = make_rollout(config, env, nets)
    evaluate = make_evaluate(config, env, nets)
    initial = make_initial_successes(config, env, primitives)
    predictor_update = make_predictor_update(nets.proximity, prox_tx, config.tp.tp_prox_batch)
    ppo_update = make_ppo_update(config, nets.policy, nets.value, ppo_tx)

    def train_step(state: TPState, eta: jax.Array) -> tuple[TPState, TPEpochMetrics]:
        del eta
        key, k_roll, k_prox, k_ppo, k_eval = jax.random.split(state.key, 5)
        agents, preds = state.agents, state.predictors
        act = TPParams(policy=agents.actor, proximity=preds.params, norm=agents.norm)
        env_state, control, data, samples, stats = rollout(act, state.env_state, state.control, preds.data, k_roll)
        norm, flat, mine, logp_old, adv, ret = ppo_inputs(config, nets, agents, samples, env_state, control)

        def prox_step(carry, k):
            params, opt = carry
            params, opt, metrics = predictor_update(params, opt, norm, data, k)
            return (params, opt), metrics

        (prox_params, prox_opt), prox_metrics = jax.lax.scan(prox_step, (preds.params, preds.opt),
                                                             jax.random.split(k_prox, config.tp.tp_prox_updates))
        (actor, value_params), ppo_opt, ppo_metrics = jax.vmap(
            ppo_update, in_axes=(0, 0, 0, None, None, None, None, 0, 0))(
            (agents.actor, agents.value), agents.opt, norm, flat, logp_old, adv, ret, mine,
            jax.random.split(k_ppo, num_k))

        agents = TransitionAgents(actor=actor, value=value_params, opt=ppo_opt, norm=norm)
        preds = Predictors(params=prox_params, opt=prox_opt, data=data)
        eval_metrics, transition_fraction = evaluate(TPParams(actor, prox_params, norm), k_eval)
        env_steps = state.env_steps + config.budget.steps_per_epoch
        metrics = TPEpochMetrics(
            env_steps=env_steps, eval=eval_metrics, train_episodes=stats.episodes,
            train_success=per_episode(stats.successes, stats.episodes),
            train_stage_fraction=per_episode(stats.stages, stats.episodes),
            eval_transition_fraction=transition_fraction, init_env_steps=state.init_env_steps,
            tp=TPTrainMetrics(rollout=stats, predictor=jax.tree.map(lambda x: x.mean(0), prox_metrics),
                              ppo=ppo_metrics, success_buffer=data.success.size, failure_buffer=data.failure.size,
                              permanent_buffer=data.permanent.size))
        new_state = TPState(agents=agents, predictors=preds, env_state=env_state, control=control, key=key,
                            env_steps=env_steps, init_env_steps=state.init_env_steps, epoch=state.epoch + 1)
        return new_state, metrics

    return Trainer(networks=nets, init=functools.partial(init_state, config, env, nets, ppo_tx, prox_tx, initial),
                   train_step=train_step)


def make_tp_grid(config: Config, env: Env, devices=None, members_at_once: int | None = None) -> GridTrainer:
    """The TP grid (seeds) as one compiled program; loads the frozen primitives of `config.tp.primitives`."""
    return GridTrainer(config, env, devices, trainer=make_tp_train(config, env, load_primitives(config)),
                       members_at_once=members_at_once)
