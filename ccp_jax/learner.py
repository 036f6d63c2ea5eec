"""The joint SAC/CSAC update of all agents, which sit on a stacked leading axis.

One call of `update` is one training loop of Algorithm 2: every agent samples
a batch from its own buffer, and all critics, actors and temperatures take one
optimiser step. Critic j receives two terms — its own (batch b_j, policy π_j)
and, for CSAC, the cross-buffer term from agent j − 1 (batch b_{j−1}, policy
π_{j−1}) — which "slots" of stacked critic parameters (see `make_update`)
wire up without any Python loop over agents.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from ccp_jax import losses
from ccp_jax.buffer import Transition
from ccp_jax.config import Config
from ccp_jax.networks import Actor, TwinCritic, sample_action

Params = Any


class AgentState(struct.PyTreeNode):
    """Every agent's learnable state; each leaf has a leading agent axis [N, ...]."""

    actor: Params
    critic: Params
    target_critic: Params
    log_alpha: jax.Array  # float32[N]
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    alpha_opt: optax.OptState


class Networks(NamedTuple):
    actor: Actor
    critic: TwinCritic
    actor_tx: optax.GradientTransformation
    critic_tx: optax.GradientTransformation
    alpha_tx: optax.GradientTransformation


def make_networks(config: Config, action_size: int) -> Networks:
    return Networks(
        actor=Actor(config.hidden, action_size),
        critic=TwinCritic(config.hidden),
        actor_tx=optax.adam(config.actor_lr),
        critic_tx=optax.adam(config.critic_lr),
        alpha_tx=optax.adam(config.alpha_lr),
    )


def init_agents(nets: Networks, key: jax.Array, num_agents: int, obs_size: int, action_size: int) -> AgentState:
    """Independently initialised agents, stacked; targets start equal to the critics."""
    obs, act = jnp.zeros((1, obs_size)), jnp.zeros((1, action_size))

    def one(k):
        k_actor, k_critic = jax.random.split(k)
        actor = nets.actor.init(k_actor, obs)
        critic = nets.critic.init(k_critic, obs, act)
        log_alpha = jnp.zeros((), jnp.float32)
        return AgentState(actor=actor, critic=critic, target_critic=critic, log_alpha=log_alpha,
                          actor_opt=nets.actor_tx.init(actor), critic_opt=nets.critic_tx.init(critic),
                          alpha_opt=nets.alpha_tx.init(log_alpha))

    return jax.vmap(one)(jax.random.split(key, num_agents))


def _min_q(critic: TwinCritic, params: Params, obs: jax.Array, act: jax.Array) -> jax.Array:
    return jnp.min(critic.apply(params, obs, act), axis=0)


class UpdateMetrics(NamedTuple):
    """Per-agent diagnostics of one update, each float32[N]."""

    q_loss: jax.Array
    pi_loss: jax.Array
    alpha: jax.Array
    log_prob: jax.Array
    q_min: jax.Array
    q_max: jax.Array
    eta_star: jax.Array
    updated: jax.Array


def make_update(config: Config, nets: Networks, action_size: int):
    """Returns `update(agents, batch, eta, ready, key) -> (agents, UpdateMetrics)`.

    batch: `Transition` with leaves [N, B, ...] (agent n's batch from B_n);
    eta: float32[N]; ready: bool[N] (agents whose buffer can fill a batch).
    """
    n_agents = config.num_agents
    cooperative = config.algo == "csac" and n_agents > 1
    agent_ids = jnp.arange(n_agents)
    # Channel reward once its subtask is done: 1 per subtask, N for the summed SAC reward.
    absorbing = (config.num_stages if config.algo == "sac" else 1.0) / (1.0 - config.gamma)
    target_entropy = -float(action_size)
    own_ids = jnp.zeros_like(agent_ids) if n_agents == 1 else agent_ids
    actor_apply = jax.vmap(nets.actor.apply)
    critic_min = jax.vmap(lambda p, o, a: _min_q(nets.critic, p, o, a))
    critic_twin = jax.vmap(nets.critic.apply)
    soft_target = jax.vmap(losses.soft_target, in_axes=(0, 0, 0, 0, 0, 0, None, None))

    # CSAC evaluates critic n on batch b_n and critic n + 1 on b_n for n < N − 1. Both sets run
    # as one stacked call over 2N − 1 "slots": slots [0, N) are (Q_n, b_n), slots [N, 2N − 1)
    # are (Q_{n+1}, b_n). Other algorithms have only the first N slots.
    if cooperative:
        slot_params = lambda t: jax.tree.map(lambda x: jnp.concatenate([x, x[1:]]), t)
        slot_data = lambda x: jnp.concatenate([x, x[:-1]])
        slot_ids = jnp.concatenate([own_ids, agent_ids[1:]])  # reward channel of each slot
    else:
        slot_params, slot_data, slot_ids = (lambda t: t), (lambda x: x), own_ids

    def channel(x: jax.Array) -> jax.Array:
        """Each slot's reward channel: [slots, B, R] -> [slots, B]."""
        return jnp.take_along_axis(x, slot_ids[:, None, None], axis=2)[..., 0]

    def total_loss(trainable, target_critic, batch: Transition, eta, ready, keys):
        actor, critic, log_alpha = trainable
        alpha = jnp.exp(jax.lax.stop_gradient(log_alpha))  # [N]
        k_next, k_pi = keys[:, 0], keys[:, 1]

        # Critic targets with π_n's next action and α_n, for j = n and j = n + 1.
        next_mean, next_log_std = actor_apply(jax.lax.stop_gradient(actor), batch.next_obs)
        next_act, next_logp = jax.vmap(sample_action)(next_mean, next_log_std, k_next)
        q_target = critic_min(slot_params(target_critic), slot_data(batch.next_obs), slot_data(next_act))
        y = soft_target(channel(slot_data(batch.rewards)), q_target, slot_data(next_logp), slot_data(alpha),
                        slot_data(batch.terminal), channel(slot_data(batch.completed)), config.gamma, absorbing)
        q_slot_loss = jax.vmap(losses.twin_q_loss)(
            critic_twin(slot_params(critic), slot_data(batch.obs), slot_data(batch.action)), y)
        q_own_loss, q_next_loss = q_slot_loss[:n_agents], q_slot_loss[n_agents:]

        # Actor: reparameterised a ~ π_n(s), critics held fixed.
        mean, log_std = actor_apply(actor, batch.obs)
        act, logp = jax.vmap(sample_action)(mean, log_std, k_pi)
        q_pi_slots = critic_min(slot_params(jax.lax.stop_gradient(critic)), slot_data(batch.obs), slot_data(act))
        q_pi, q_pi_next = q_pi_slots[:n_agents], q_pi_slots[n_agents:]  # [N, B], [N − 1, B]
        pi_loss = jax.vmap(losses.sac_actor_loss)(logp, q_pi, alpha)
        coop_loss = jax.vmap(losses.coop_actor_loss, in_axes=(0, 0, 0, 0, 0, None))
        eta_star = jnp.ones((n_agents,))
        if cooperative:
            lead = slice(0, n_agents - 1)
            pi_loss = pi_loss.at[lead].set(coop_loss(logp[lead], q_pi[lead], q_pi_next, eta[lead], alpha[lead],
                                                     config.norm_eps))
            eta_star = eta_star.at[lead].set(jax.vmap(losses.eta_star, in_axes=(0, 0, None))(
                q_pi[lead], q_pi_next, config.norm_eps))
        if config.normalise_last:  # η_N = 1 on the normalised own critic
            last = slice(n_agents - 1, n_agents)
            pi_loss = pi_loss.at[last].set(coop_loss(logp[last], q_pi[last], q_pi[last], jnp.ones((1,)),
                                                     alpha[last], config.norm_eps))
        a_loss = jax.vmap(losses.alpha_loss, in_axes=(0, 0, None))(log_alpha, logp, target_entropy)

        mask = ready.astype(jnp.float32)
        # Critic j's cross term comes from agent j − 1's batch, so it is masked by that agent's readiness.
        total = jnp.sum(mask * (q_own_loss + pi_loss + a_loss)) + jnp.sum(slot_data(mask)[n_agents:] * q_next_loss)
        q_loss = q_own_loss.at[: n_agents - 1].add(q_next_loss) if cooperative else q_own_loss
        metrics = UpdateMetrics(q_loss=q_loss, pi_loss=pi_loss, alpha=alpha, log_prob=jnp.mean(logp, -1),
                                q_min=jnp.min(q_pi, -1), q_max=jnp.max(q_pi, -1), eta_star=eta_star,
                                updated=mask)
        return total, metrics

    def step_opt(tx, params, grads, opt_state, mask):
        updates, new_opt = tx.update(grads, opt_state, params)
        new_params = optax.apply_updates(params, updates)
        keep = lambda new, old: jnp.where(mask, new, old)
        return jax.tree.map(keep, new_params, params), jax.tree.map(keep, new_opt, opt_state)

    def update(agents: AgentState, batch: Transition, eta: jax.Array, ready: jax.Array, key: jax.Array):
        keys = jax.random.split(key, (n_agents, 2))
        trainable = (agents.actor, agents.critic, agents.log_alpha)
        grads, metrics = jax.grad(total_loss, has_aux=True)(trainable, agents.target_critic, batch, eta, ready, keys)
        g_actor, g_critic, g_alpha = grads
        # A critic moves when its own buffer or (CSAC) the previous agent's buffer is ready.
        critic_ready = ready.at[1:].set(ready[1:] | ready[:-1]) if cooperative else ready
        vstep = lambda tx: jax.vmap(lambda p, g, o, m: step_opt(tx, p, g, o, m))
        actor, actor_opt = vstep(nets.actor_tx)(agents.actor, g_actor, agents.actor_opt, ready)
        critic, critic_opt = vstep(nets.critic_tx)(agents.critic, g_critic, agents.critic_opt, critic_ready)
        log_alpha, alpha_opt = vstep(nets.alpha_tx)(agents.log_alpha, g_alpha, agents.alpha_opt, ready)
        target = optax.incremental_update(critic, agents.target_critic, config.tau)
        return AgentState(actor=actor, critic=critic, target_critic=target, log_alpha=log_alpha,
                          actor_opt=actor_opt, critic_opt=critic_opt, alpha_opt=alpha_opt), metrics

    return update
