"""The joint SAC/CSAC update of all agents, which sit on a stacked leading axis.

One call of `update` is one training loop of Algorithm 2: every agent samples
a batch from its own buffer, and all critics, actors and temperatures take one
optimiser step. Critic j receives two terms — its own (batch b_j, policy π_j)
and, for CSAC, the cross-buffer term from agent j − 1 (batch b_{j−1}, policy
π_{j−1}) — which "slots" of stacked critic parameters (see `make_update`)
wire up without any Python loop over agents.
"""
from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from ccp_jax import buffer as replay
from ccp_jax import eta as ratios
from ccp_jax import losses
from ccp_jax.buffer import ReplayBuffer, Transition
from ccp_jax.config import Config
from ccp_jax.networks import Actor, TwinCritic, squashed_gaussian

Params = Any


class NormState(struct.PyTreeNode):
    """Running (EMA) bounds of each agent's critics on its own batches, [N, 2]: [:, 0] own, [:, 1] next.

    They start at a channel's possible value range [0, 1/(1 − γ)] (rewards lie
    in [0, 1]), so a critic that is still flat is not blown up to full scale.
    """

    lo: jax.Array
    hi: jax.Array


class AgentState(struct.PyTreeNode):
    """Every agent's learnable state; each leaf has a leading agent axis [N, ...]."""

    norm: NormState
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
        actor=Actor(config.hidden, action_size, init_scheme=config.network_init),
        critic=TwinCritic(config.hidden, init_scheme=config.network_init),
        actor_tx=optax.adam(config.actor_lr),
        critic_tx=optax.adam(config.critic_lr),
        alpha_tx=optax.adam(config.alpha_lr),
    )


def init_agents(nets: Networks, key: jax.Array, num_agents: int, obs_size: int, action_size: int,
                value_range: float = 1.0, initial_alpha: float = 1.0) -> AgentState:
    """Independently initialised agents, stacked; targets start equal to the critics.

    `value_range` is the largest value a critic can take (1/(1 − γ) for rewards in [0, 1]);
    `initial_alpha` every temperature's starting value.
    """
    obs, act = jnp.zeros((1, obs_size)), jnp.zeros((1, action_size))

    def one(k):
        k_actor, k_critic = jax.random.split(k)
        actor = nets.actor.init(k_actor, obs)
        critic = nets.critic.init(k_critic, obs, act)
        log_alpha = jnp.full((), math.log(initial_alpha), jnp.float32)
        norm = NormState(lo=jnp.zeros((2,)), hi=jnp.full((2,), value_range, jnp.float32))  # not weak-typed: no recompile
        return AgentState(norm=norm, actor=actor, critic=critic, target_critic=critic, log_alpha=log_alpha,
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
    eta_star: jax.Array  # from this batch's ranges
    eta_used: jax.Array  # the ratio the actor loss used (η, or the running η* for "auto")
    range_own: jax.Array  # Ran(Q_n) the normaliser divided by
    range_next: jax.Array  # Ran(Q_{n+1}) the normaliser divided by
    updated: jax.Array


class UpdateNoise(NamedTuple):
    """The standard-normal draws of one update, [N, B, a] each.

    `next` draws a' ~ π_n(s') for the critic targets and `pi` a ~ π_n(s) for the actor loss;
    `successor` ([N − 1, B, a], empty unless `next_action="acting"`) a' ~ π_{n+1}(s').
    """

    next: jax.Array
    pi: jax.Array
    successor: jax.Array


class Learner(NamedTuple):
    update: Callable  # (agents, batch, eta, ready, key) -> (agents, UpdateMetrics)
    draw_noise: Callable  # (key, batch_size) -> UpdateNoise: what `update` draws from its key
    update_with_noise: Callable  # (agents, batch, eta, ready, UpdateNoise) -> (agents, UpdateMetrics)
    action_pulls: Callable  # (agents, batch, eta, key) -> (float32[N], float32[N])


def is_cooperative(config: Config) -> bool:
    """CSAC with more than one agent: critics get cross-buffer terms and actors a next critic."""
    return config.algo == "csac" and config.num_agents > 1


def critic_slots(config: Config) -> int:
    """Critic evaluations in one member's update, the slots `make_learner` stacks: 2N − 1 when cooperative, else N."""
    n = config.num_agents
    return 2 * n - 1 if is_cooperative(config) else n


def make_learner(config: Config, nets: Networks, action_size: int) -> Learner:
    """Returns `Learner.update(agents, batch, eta, ready, key) -> (agents, UpdateMetrics)`.

    batch: `Transition` with leaves [N, B, ...] (agent n's batch from B_n);
    eta: float32[N] (NaN: "auto"); ready: bool[N] (agents whose buffer can fill a batch).
    `update` is `update_with_noise` of `draw_noise(key, B)`: a loop of updates can draw
    all of its noise at once, outside the loop, and get the same numbers.
    """
    n_agents = config.num_agents
    cooperative = is_cooperative(config)
    agent_ids = jnp.arange(n_agents)
    target_entropy = -float(action_size) if config.target_entropy is None else config.target_entropy
    own_ids = jnp.zeros_like(agent_ids) if n_agents == 1 else agent_ids
    actor_apply = jax.vmap(nets.actor.apply)
    squash = jax.vmap(functools.partial(squashed_gaussian, tanh_log_prob=config.tanh_log_prob))
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

    has_next = jnp.arange(n_agents) < n_agents - 1
    coop_actor = (has_next & cooperative) | ((agent_ids == n_agents - 1) & config.normalise_last)

    def pair(q_slots: jax.Array) -> jax.Array:
        """Own and next critic values per agent, [slots, B] -> [N, 2, B]; without a next critic, own twice."""
        q_own = q_slots[:n_agents]
        q_next = jnp.concatenate([q_slots[n_agents:], q_own[-1:]]) if cooperative else q_own
        return jnp.stack([q_own, q_next], axis=1)

    def normalised(q_pair, eta, norm: NormState, ready):
        """Q̂ of own and next critics [N, 2, B] under `config.normaliser`, the ratios used, new running bounds."""
        bounds = jax.lax.stop_gradient(q_pair)
        b_lo, b_hi = bounds.min(-1), bounds.max(-1)  # [N, 2]
        e_lo = norm.lo + config.norm_ema_rate * (b_lo - norm.lo)
        e_hi = norm.hi + config.norm_ema_rate * (b_hi - norm.hi)
        if config.normaliser == "ema":
            lo, scale = e_lo, e_hi - e_lo
        elif config.normaliser == "floor":
            lo, scale = b_lo, jnp.maximum(b_hi - b_lo, config.norm_floor)
        elif config.normaliser == "none":
            lo, scale = jnp.zeros_like(b_lo), jnp.ones_like(b_hi)
        else:
            lo, scale = b_lo, b_hi - b_lo
        q_hat = losses.normalise(q_pair, config.norm_eps, lo[..., None], scale[..., None])
        eta_used = ratios.actor_eta(eta, e_hi[:, 0] - e_lo[:, 0], e_hi[:, 1] - e_lo[:, 1], has_next & cooperative,
                                    config)
        keep = ready[:, None]
        new = NormState(lo=jnp.where(keep, e_lo, norm.lo), hi=jnp.where(keep, e_hi, norm.hi))
        eta_star = jnp.where(has_next, ratios.eta_star(b_hi[:, 0] - b_lo[:, 0], b_hi[:, 1] - b_lo[:, 1],
                                                        config.norm_eps), 1.0)
        diag = dict(eta_star=eta_star, eta_used=eta_used, range_own=scale[:, 0],
                    range_next=jnp.where(has_next, scale[:, 1], 0.0))
        return q_hat, eta_used, new, diag

    def coop_units(diag) -> jax.Array:
        """Per-agent factor on C_n, float32[N]: "own" undoes the own critic's scaling, so η = 1 is Naive's actor loss."""
        return diag["range_own"] + config.norm_eps if config.coop_scale == "own" else jnp.ones((n_agents,))

    acting_next = cooperative and config.next_action == "acting"

    def normal(keys: jax.Array, batch_size: int) -> jax.Array:
        """One standard-normal [B, a] per key: keys [K] -> [K, B, a]."""
        return jax.vmap(lambda k: jax.random.normal(k, (batch_size, action_size)))(keys)

    def draw_noise(key: jax.Array, batch_size: int) -> UpdateNoise:
        keys = jax.random.split(key, (n_agents, 2))
        k_next, k_pi = keys[:, 0], keys[:, 1]
        successor = (normal(jax.vmap(lambda k: jax.random.fold_in(k, 1))(k_next[:-1]), batch_size) if acting_next
                     else jnp.zeros((0, batch_size, action_size)))
        return UpdateNoise(next=normal(k_next, batch_size), pi=normal(k_pi, batch_size), successor=successor)

    def successor_takes_over(actor, batch: Transition, next_act, next_logp, next_alpha, alpha, noise):
        """Where agent n's s' already lies in stage n + 1, a' ~ π_{n+1}(s') with α_{n+1}: the policy acting there.

        next_act [N, B, a], next_logp and next_alpha [N, B] are π_n's; returns them with those rows replaced.
        """
        successors = jax.tree.map(lambda x: x[1:], actor)
        mean, log_std = actor_apply(successors, batch.next_obs[:-1])
        act, logp = squash(mean, log_std, noise)  # [N − 1, B, a], [N − 1, B]
        crossed = batch.next_stage[:-1] > agent_ids[:-1, None]  # [N − 1, B]
        lead = slice(0, n_agents - 1)
        return (next_act.at[lead].set(jnp.where(crossed[..., None], act, next_act[lead])),
                next_logp.at[lead].set(jnp.where(crossed, logp, next_logp[lead])),
                next_alpha.at[lead].set(jnp.where(crossed, alpha[1:, None], next_alpha[lead])))

    def total_loss(trainable, target_critic, norm_state, batch: Transition, eta, ready, noise: UpdateNoise):
        actor, critic, log_alpha = trainable
        alpha = jnp.exp(jax.lax.stop_gradient(log_alpha))  # [N]

        # Critic targets with π_n's next action and α_n, for j = n and j = n + 1.
        frozen_actor = jax.lax.stop_gradient(actor)
        next_mean, next_log_std = actor_apply(frozen_actor, batch.next_obs)
        next_act, next_logp = squash(next_mean, next_log_std, noise.next)
        next_alpha = jnp.broadcast_to(alpha[:, None], next_logp.shape)  # [N, B]
        if acting_next:
            next_act, next_logp, next_alpha = successor_takes_over(frozen_actor, batch, next_act, next_logp,
                                                                   next_alpha, alpha, noise.successor)
        q_target = critic_min(slot_params(target_critic), slot_data(batch.next_obs), slot_data(next_act))
        y = soft_target(channel(slot_data(batch.rewards)), q_target, slot_data(next_logp), slot_data(next_alpha),
                        slot_data(batch.terminal), channel(slot_data(batch.completed)), config.gamma,
                        config.value_bound)  # a done subtask's value
        q_slot_loss = jax.vmap(losses.twin_q_loss)(
            critic_twin(slot_params(critic), slot_data(batch.obs), slot_data(batch.action)), y)
        q_own_loss, q_next_loss = q_slot_loss[:n_agents], q_slot_loss[n_agents:]

        # Actor: reparameterised a ~ π_n(s), critics held fixed.
        mean, log_std = actor_apply(actor, batch.obs)
        act, logp = squash(mean, log_std, noise.pi)
        frozen = slot_params(jax.lax.stop_gradient(critic))
        q_pi_slots = critic_min(frozen, slot_data(batch.obs), slot_data(act))
        q_pi = q_pi_slots[:n_agents]  # [N, B]
        pi_loss = jax.vmap(losses.sac_actor_loss)(logp, q_pi, alpha)
        norm, diag = norm_state, {}
        if cooperative or config.normalise_last:
            # Own and next critic per agent, [N, 2, B]; an agent without a next critic repeats its own.
            q_hat, eta_used, norm, diag = normalised(pair(q_pi_slots), eta, norm_state, ready)
            units = coop_units(diag)
            coop = jax.vmap(losses.coop_actor_loss)(logp, q_hat[:, 0], q_hat[:, 1], eta_used, alpha, units)
            pi_loss = jnp.where(coop_actor, coop, pi_loss)
        a_loss = jax.vmap(losses.alpha_loss, in_axes=(0, 0, None))(log_alpha, logp, target_entropy)

        mask = ready.astype(jnp.float32)
        # Critic j's cross term comes from agent j − 1's batch, so it is masked by that agent's readiness.
        total = jnp.sum(mask * (q_own_loss + pi_loss + a_loss)) + jnp.sum(slot_data(mask)[n_agents:] * q_next_loss)
        q_loss = q_own_loss.at[: n_agents - 1].add(q_next_loss) if cooperative else q_own_loss
        ones, zeros = jnp.ones((n_agents,)), jnp.zeros((n_agents,))
        metrics = UpdateMetrics(q_loss=q_loss, pi_loss=pi_loss, alpha=alpha, log_prob=jnp.mean(logp, -1),
                                q_min=jnp.min(q_pi, -1), q_max=jnp.max(q_pi, -1),
                                eta_star=diag.get("eta_star", ones), eta_used=diag.get("eta_used", ones),
                                range_own=diag.get("range_own", zeros), range_next=diag.get("range_next", zeros),
                                updated=mask)
        return total, (metrics, norm)

    def step_opt(tx, params, grads, opt_state, mask):
        updates, new_opt = tx.update(grads, opt_state, params)
        new_params = optax.apply_updates(params, updates)
        keep = lambda new, old: jnp.where(mask, new, old)
        return jax.tree.map(keep, new_params, params), jax.tree.map(keep, new_opt, opt_state)

    def update_with_noise(agents: AgentState, batch: Transition, eta: jax.Array, ready: jax.Array,
                          noise: UpdateNoise):
        trainable = (agents.actor, agents.critic, agents.log_alpha)
        grads, (metrics, norm) = jax.grad(total_loss, has_aux=True)(trainable, agents.target_critic, agents.norm,
                                                                   batch, eta, ready, noise)
        g_actor, g_critic, g_alpha = grads
        # A critic moves when its own buffer or (CSAC) the previous agent's buffer is ready.
        critic_ready = ready.at[1:].set(ready[1:] | ready[:-1]) if cooperative else ready
        vstep = lambda tx: jax.vmap(lambda p, g, o, m: step_opt(tx, p, g, o, m))
        actor, actor_opt = vstep(nets.actor_tx)(agents.actor, g_actor, agents.actor_opt, ready)
        critic, critic_opt = vstep(nets.critic_tx)(agents.critic, g_critic, agents.critic_opt, critic_ready)
        log_alpha, alpha_opt = vstep(nets.alpha_tx)(agents.log_alpha, g_alpha, agents.alpha_opt, ready)
        target = optax.incremental_update(critic, agents.target_critic, config.tau)
        return AgentState(norm=norm, actor=actor, critic=critic, target_critic=target, log_alpha=log_alpha,
                          actor_opt=actor_opt, critic_opt=critic_opt, alpha_opt=alpha_opt), metrics

    def update(agents: AgentState, batch: Transition, eta: jax.Array, ready: jax.Array, key: jax.Array):
        return update_with_noise(agents, batch, eta, ready, draw_noise(key, batch.obs.shape[1]))

    def action_pulls(agents: AgentState, batch: Transition, eta: jax.Array, key: jax.Array):
        """Each critic's pull on agent n's actions: mean ‖∂(η Q̂_n)/∂a‖ and ‖∂((1 − η) Q̂_{n+1})/∂a‖, float32[N] each.

        A diagnostic of which critic drives the actor (computed once per epoch,
        with the running bounds as they stand, without updating them).
        """
        if not (cooperative or config.normalise_last):
            zeros = jnp.zeros((n_agents,))
            return zeros, zeros
        mean, log_std = actor_apply(agents.actor, batch.obs)
        act, _ = squash(mean, log_std, normal(jax.random.split(key, n_agents), batch.obs.shape[1]))
        slots = slot_params(agents.critic)

        def weighted(a):
            q_hat, eta_used, _, diag = normalised(pair(critic_min(slots, slot_data(batch.obs), slot_data(a))), eta,
                                                  agents.norm, jnp.zeros((n_agents,), bool))
            units = coop_units(diag)[:, None]  # from the normaliser's bounds: already constants
            return (units * eta_used[:, None] * q_hat[:, 0],
                    units * jnp.where(has_next[:, None], 1 - eta_used[:, None], 0.0) * q_hat[:, 1])

        pulls = []
        for term in range(2):
            # q_hat's bounds are constants, so this is the gradient the actor loss sees from that term.
            g = jax.grad(lambda a: weighted(a)[term].sum())(act)
            pulls.append(jnp.linalg.norm(g, axis=-1).mean(-1))
        return pulls[0], pulls[1]

    return Learner(update=update, draw_noise=draw_noise, update_with_noise=update_with_noise,
                   action_pulls=action_pulls)


def train_loops(learner: Learner, agents: AgentState, buffer: ReplayBuffer, eta: jax.Array, ready: jax.Array,
                key: jax.Array, loops: int, batch_size: int) -> tuple[AgentState, UpdateMetrics]:
    """`loops` joint updates, each on fresh batches from `buffer`: (agents, UpdateMetrics with leaves [loops, N]).

    Loop i draws from the i-th key of `key`; all loops' batch indices and noise are drawn at once,
    before the loop (the same draws as inside it). Drawn inside it, each is a small random-number
    loop run in series with the update: on a CPU the 1000 updates of the yardstick's epoch
    (docs/design.md#the-learning-yardstick) run ≈ 20 % faster without them, the whole epoch 2 – 13 %.
    Loop i also gathers loop i + 1's batch (the same batches), so that gather overlaps the update
    instead of preceding it (experiments/bench/epoch_versions.py).
    """
    loop_keys = jax.vmap(jax.random.split)(jax.random.split(key, loops))
    idx = jax.vmap(lambda k: replay.sample_indices(buffer.size, k, batch_size))(loop_keys[:, 0])
    noise = jax.vmap(lambda k: learner.draw_noise(k, batch_size))(loop_keys[:, 1])
    ahead = jnp.roll(idx, -1, axis=0)  # the last loop gathers the first batch again, unused

    def loop(carry, drawn):
        agents, batch = carry
        next_idx, noise = drawn
        agents, metrics = learner.update_with_noise(agents, batch, eta, ready, noise)
        return (agents, replay.gather(buffer, next_idx)), metrics

    (agents, _), metrics = jax.lax.scan(loop, (agents, replay.gather(buffer, idx[0])), (ahead, noise))
    return agents, metrics
