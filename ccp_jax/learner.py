"""The joint SAC/CSAC update of all agents, which sit on a stacked leading axis.

One call of `update` is one training loop of Algorithm 2 (docs/design.md#the-method): every agent
samples a batch from its own buffer, then `update_critic`, `update_actor` and `update_alpha` each take
one optimiser step for all agents, on the pure losses of `losses.py`, with the ratios η of `eta.py`.
Critic j receives two terms — its own (batch b_j, policy π_j) and, for CSAC, the cross-buffer term from
agent j − 1 (batch b_{j−1}, policy π_{j−1}) — which the critic "slots" of `Chain` wire up without any
Python loop over agents.
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
        actor=Actor(config.sac.hidden, action_size, init_scheme=config.ablations.network_init),
        critic=TwinCritic(config.sac.hidden, init_scheme=config.ablations.network_init),
        actor_tx=optax.adam(config.sac.actor_lr),
        critic_tx=optax.adam(config.sac.critic_lr),
        alpha_tx=optax.adam(config.sac.alpha_lr),
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
    """The update of `make_learner`, in the forms its callers need."""

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


class Chain(NamedTuple):
    """How the stacked agents reach each other's critics (built once by `make_chain`).

    CSAC evaluates critic n on batch b_n and, for n < N − 1, critic n + 1 on b_n. Both sets run as one
    stacked call over 2N − 1 "slots": slots [0, N) are (Q_n, b_n), slots [N, 2N − 1) are (Q_{n+1}, b_n).
    Other algorithms have only the first N slots.
    """

    num_agents: int
    cooperative: bool  # `is_cooperative`
    agent_ids: jax.Array  # int32[N]
    slot_ids: jax.Array  # int32[slots]: the reward channel each slot's critic learns
    has_next: jax.Array  # bool[N]: agents followed by another
    coop_actor: jax.Array  # bool[N]: actors on the cooperative objective (a next critic, or `normalise_last`)

    def slot_params(self, params: Params) -> Params:
        """Each slot's critic parameters: leaves [N, ...] -> [slots, ...]."""
        return jax.tree.map(lambda x: jnp.concatenate([x, x[1:]]), params) if self.cooperative else params

    def slot_data(self, x: jax.Array) -> jax.Array:
        """Each slot's data, agent n's for both of its slots: [N, ...] -> [slots, ...]."""
        return jnp.concatenate([x, x[:-1]]) if self.cooperative else x

    def channel(self, x: jax.Array) -> jax.Array:
        """Each slot's reward channel: [slots, B, R] -> [slots, B]."""
        return jnp.take_along_axis(x, self.slot_ids[:, None, None], axis=2)[..., 0]

    def pair(self, q_slots: jax.Array) -> jax.Array:
        """Own and next critic values per agent, [slots, B] -> [N, 2, B]; without a next critic, own twice."""
        q_own = q_slots[: self.num_agents]
        q_next = jnp.concatenate([q_slots[self.num_agents:], q_own[-1:]]) if self.cooperative else q_own
        return jnp.stack([q_own, q_next], axis=1)

    def critic_ready(self, ready: jax.Array) -> jax.Array:
        """bool[N]: the critics that move, those whose own buffer or (CSAC) the previous agent's is `ready`."""
        return ready.at[1:].set(ready[1:] | ready[:-1]) if self.cooperative else ready


def make_chain(config: Config) -> Chain:
    """The `Chain` of `config`'s agents."""
    n, cooperative = config.num_agents, is_cooperative(config)
    agent_ids = jnp.arange(n)
    slot_ids = jnp.concatenate([agent_ids, agent_ids[1:]]) if cooperative else agent_ids
    has_next = agent_ids < n - 1
    coop_actor = (has_next & cooperative) | ((agent_ids == n - 1) & config.ablations.normalise_last)
    return Chain(num_agents=n, cooperative=cooperative, agent_ids=agent_ids, slot_ids=slot_ids, has_next=has_next,
                 coop_actor=coop_actor)


class Setup(NamedTuple):
    """What the update's functions share: the run's settings, its networks and how its agents are chained."""

    config: Config
    nets: Networks
    chain: Chain
    action_size: int

    @property
    def target_entropy(self) -> float:
        """H̄ of the temperature loss: −|A| (RLkit's) unless the config sets one."""
        return -float(self.action_size) if self.config.sac.target_entropy is None else self.config.sac.target_entropy

    @property
    def acting_next(self) -> bool:
        """Whether a critic target at s' in stage n + 1 takes π_{n+1}'s action (`next_action="acting"`)."""
        return self.chain.cooperative and self.config.ablations.next_action == "acting"


def make_learner(config: Config, nets: Networks, action_size: int) -> Learner:
    """Returns `Learner.update(agents, batch, eta, ready, key) -> (agents, UpdateMetrics)`.

    batch: `Transition` with leaves [N, B, ...] (agent n's batch from B_n);
    eta: float32[N] (NaN: "auto"); ready: bool[N] (agents whose buffer can fill a batch).
    `update` is `update_with_noise` of `draw_noise(key, B)`: a loop of updates can draw
    all of its noise at once, outside the loop, and get the same numbers.
    """
    setup = Setup(config=config, nets=nets, chain=make_chain(config), action_size=action_size)
    with_noise = functools.partial(update_with_noise, setup)
    noise = functools.partial(draw_noise, setup)

    def update(agents: AgentState, batch: Transition, eta: jax.Array, ready: jax.Array, key: jax.Array):
        return with_noise(agents, batch, eta, ready, noise(key, batch.obs.shape[1]))

    return Learner(update=update, draw_noise=noise, update_with_noise=with_noise,
                   action_pulls=functools.partial(action_pulls, setup))


# ------------------------------------------------------------------ one update

def update_with_noise(setup: Setup, agents: AgentState, batch: Transition, eta: jax.Array, ready: jax.Array,
                      noise: UpdateNoise) -> tuple[AgentState, UpdateMetrics]:
    """One training loop of Algorithm 2 for every agent: critics, actors and temperatures each take a step.

    All three losses read the parameters from before the step: the critics' targets and the actors'
    objective use this step's α, the actors' objective this step's critics (held fixed).
    """
    alpha = jnp.exp(agents.log_alpha)  # float32[N]
    targets = critic_targets(setup, agents.actor, agents.target_critic, batch, alpha, noise)
    critic, critic_opt, q_loss = update_critic(setup, agents, batch, targets, ready)
    actor, actor_opt, norm, pi = update_actor(setup, agents, batch, eta, alpha, ready, noise)
    log_alpha, alpha_opt = update_alpha(setup, agents, pi.log_prob, ready)
    target_critic = optax.incremental_update(critic, agents.target_critic, setup.config.sac.tau)
    agents = AgentState(norm=norm, actor=actor, critic=critic, target_critic=target_critic, log_alpha=log_alpha,
                        actor_opt=actor_opt, critic_opt=critic_opt, alpha_opt=alpha_opt)
    metrics = UpdateMetrics(q_loss=q_loss, pi_loss=pi.loss, alpha=alpha, log_prob=jnp.mean(pi.log_prob, -1),
                            q_min=jnp.min(pi.q, -1), q_max=jnp.max(pi.q, -1), eta_star=pi.eta_star,
                            eta_used=pi.eta_used, range_own=pi.range_own, range_next=pi.range_next,
                            updated=ready.astype(jnp.float32))
    return agents, metrics


def critic_targets(setup: Setup, actor: Params, target_critic: Params, batch: Transition, alpha: jax.Array,
                   noise: UpdateNoise) -> jax.Array:
    """Algorithm 2's critic targets y [slots, B]; alpha float32[N].

    Slot (j, b_n) gets r_j + γ(Q̄_j(s', a') − α_n log π_n(a'|s')), a' ~ π_n(s'): agent n's policy and
    temperature for both critics it trains (`losses.soft_target` for terminations and done subtasks).
    """
    c = setup.chain
    next_act, next_logp = _policy(setup, actor, batch.next_obs, noise.next)
    next_alpha = jnp.broadcast_to(alpha[:, None], next_logp.shape)  # [N, B]
    if setup.acting_next:
        next_act, next_logp, next_alpha = successor_takes_over(setup, actor, batch, next_act, next_logp, next_alpha,
                                                               alpha, noise.successor)
    q_next = _min_q(setup, c.slot_params(target_critic), c.slot_data(batch.next_obs), c.slot_data(next_act))
    soft_target = jax.vmap(losses.soft_target, in_axes=(0, 0, 0, 0, 0, 0, None, None))
    return soft_target(c.channel(c.slot_data(batch.rewards)), q_next, c.slot_data(next_logp), c.slot_data(next_alpha),
                       c.slot_data(batch.terminal), c.channel(c.slot_data(batch.completed)), setup.config.sac.gamma,
                       setup.config.value_bound)  # a done subtask's value


def successor_takes_over(setup: Setup, actor: Params, batch: Transition, next_act: jax.Array, next_logp: jax.Array,
                         next_alpha: jax.Array, alpha: jax.Array,
                         noise: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Where agent n's s' already lies in stage n + 1, a' ~ π_{n+1}(s') with α_{n+1}: the policy acting there.

    next_act [N, B, a], next_logp and next_alpha [N, B] are π_n's; noise [N − 1, B, a]; returns them with
    those rows replaced (a choice the paper leaves open: docs/design.md#decisions-the-paper-leaves-open).
    """
    n = setup.chain.num_agents
    successors = jax.tree.map(lambda x: x[1:], actor)
    act, logp = _policy(setup, successors, batch.next_obs[:-1], noise)  # [N − 1, B, a], [N − 1, B]
    crossed = batch.next_stage[:-1] > setup.chain.agent_ids[:-1, None]  # [N − 1, B]
    lead = slice(0, n - 1)
    return (next_act.at[lead].set(jnp.where(crossed[..., None], act, next_act[lead])),
            next_logp.at[lead].set(jnp.where(crossed, logp, next_logp[lead])),
            next_alpha.at[lead].set(jnp.where(crossed, alpha[1:, None], next_alpha[lead])))


def update_critic(setup: Setup, agents: AgentState, batch: Transition, targets: jax.Array,
                  ready: jax.Array) -> tuple[Params, optax.OptState, jax.Array]:
    """Every critic's step on Eq. (1) towards `targets` [slots, B]: (critic, critic_opt, q_loss float32[N]).

    Critic j's loss sums its own term (batch b_j) and, for CSAC, agent j − 1's cross-buffer term (batch
    b_{j−1}), each counted only where that batch's agent is `ready`.
    """
    c, n = setup.chain, setup.chain.num_agents
    mask = ready.astype(jnp.float32)

    def loss(critic: Params):
        q = jax.vmap(setup.nets.critic.apply)(c.slot_params(critic), c.slot_data(batch.obs), c.slot_data(batch.action))
        per_slot = jax.vmap(losses.twin_q_loss)(q, targets)
        own, cross = per_slot[:n], per_slot[n:]
        return jnp.sum(mask * own) + jnp.sum(c.slot_data(mask)[n:] * cross), (own, cross)

    grads, (own, cross) = jax.grad(loss, has_aux=True)(agents.critic)
    critic, critic_opt = _masked_step(setup.nets.critic_tx, agents.critic, grads, agents.critic_opt,
                                      c.critic_ready(ready))
    return critic, critic_opt, own.at[: n - 1].add(cross) if c.cooperative else own


class ActorTerms(NamedTuple):
    """Each agent's actor loss and what it was made of, for a ~ π_n(s) on agent n's batch."""

    loss: jax.Array  # float32[N]
    log_prob: jax.Array  # float32[N, B]
    q: jax.Array  # float32[N, B]: Q_n(setup, a), the own critic's min of its twin
    eta_star: jax.Array  # float32[N]: η* of this batch's ranges (1 without a next critic)
    eta_used: jax.Array  # float32[N]: the ratio the loss used (η, or "auto"'s)
    range_own: jax.Array  # float32[N]: Ran(Q_n) the normaliser divided by (0 without a normaliser)
    range_next: jax.Array  # float32[N]: Ran(Q_{n+1}) the normaliser divided by (0 without a next critic)


def update_actor(setup: Setup, agents: AgentState, batch: Transition, eta: jax.Array, alpha: jax.Array,
                 ready: jax.Array, noise: UpdateNoise) -> tuple[Params, optax.OptState, NormState, ActorTerms]:
    """Every ready actor's step on its loss (`actor_terms`), reparameterised a ~ π_n(s) with `noise.pi`.

    Returns (actor, actor_opt, the normaliser's running bounds after this batch, the loss's `ActorTerms`).
    """
    mask = ready.astype(jnp.float32)

    def loss(actor: Params):
        act, log_prob = _policy(setup, actor, batch.obs, noise.pi)
        terms, norm = actor_terms(setup, agents.critic, agents.norm, batch.obs, act, log_prob, eta, alpha, ready)
        return jnp.sum(mask * terms.loss), (terms, norm)

    grads, (terms, norm) = jax.grad(loss, has_aux=True)(agents.actor)
    actor, actor_opt = _masked_step(setup.nets.actor_tx, agents.actor, grads, agents.actor_opt, ready)
    return actor, actor_opt, norm, terms


def actor_terms(setup: Setup, critic: Params, norm: NormState, obs: jax.Array, act: jax.Array, log_prob: jax.Array,
                eta: jax.Array, alpha: jax.Array, ready: jax.Array) -> tuple[ActorTerms, NormState]:
    """Each agent's actor loss for actions act [N, B, a] at obs [N, B, o], critics held fixed.

    Agents with a next critic (and the last one with `normalise_last`) minimise mean(α log π − C_n),
    C_n = η Q̂_n + (1 − η) Q̂_{n+1} (Eq. (2), (3)), with the normalised Q̂ of `normalised_pair`; the others
    SAC's mean(α log π − Q_n).
    """
    c, config, n = setup.chain, setup.config, setup.chain.num_agents
    q_slots = _min_q(setup, c.slot_params(jax.lax.stop_gradient(critic)), c.slot_data(obs), c.slot_data(act))
    q = q_slots[:n]
    sac = jax.vmap(losses.sac_actor_loss)(log_prob, q, alpha)
    ones, zeros = jnp.ones((n,)), jnp.zeros((n,))
    terms = ActorTerms(loss=sac, log_prob=log_prob, q=q, eta_star=ones, eta_used=ones, range_own=zeros,
                       range_next=zeros)
    if not (c.cooperative or config.ablations.normalise_last):
        return terms, norm
    q_hat, norm, scaled = normalised_pair(setup, c.pair(q_slots), eta, norm, ready)
    units = losses.coop_units(config.ablations.coop_scale, scaled.range_own, config.ccp.norm_eps)
    coop = jax.vmap(losses.coop_actor_loss)(log_prob, q_hat[:, 0], q_hat[:, 1], scaled.eta_used, alpha, units)
    return terms._replace(loss=jnp.where(c.coop_actor, coop, sac), **scaled._asdict()), norm


class Scaled(NamedTuple):
    """How `normalised_pair` weighed and scaled each agent's critics, float32[N] each (see `ActorTerms`)."""

    eta_star: jax.Array
    eta_used: jax.Array
    range_own: jax.Array
    range_next: jax.Array


def normalised_pair(setup: Setup, q_pair: jax.Array, eta: jax.Array, norm: NormState,
                    ready: jax.Array) -> tuple[jax.Array, NormState, Scaled]:
    """Q̂ of own and next critics, q_pair [N, 2, B] -> [N, 2, B], under `config.ablations.normaliser` (`losses.normalise_batch`).

    Also returns the running bounds after this batch (moved only for `ready` agents) and `Scaled`: the
    ratios η the actor loss uses (`eta.actor_eta`, from the running ranges) and the ranges divided by.
    """
    config, c = setup.config, setup.chain
    q = losses.normalise_batch(q_pair, norm.lo, norm.hi, config.ablations.normaliser, config.ccp.norm_eps, config.ccp.norm_ema_rate,
                               config.ablations.norm_floor)
    running = q.running_hi - q.running_lo  # [N, 2]
    eta_used = ratios.actor_eta(eta, running[:, 0], running[:, 1], c.has_next & c.cooperative, config)
    keep = ready[:, None]
    norm = NormState(lo=jnp.where(keep, q.running_lo, norm.lo), hi=jnp.where(keep, q.running_hi, norm.hi))
    eta_star = jnp.where(c.has_next, ratios.eta_star(q.batch_range[:, 0], q.batch_range[:, 1], config.ccp.norm_eps), 1.0)
    return q.q_hat, norm, Scaled(eta_star=eta_star, eta_used=eta_used, range_own=q.scale[:, 0],
                                 range_next=jnp.where(c.has_next, q.scale[:, 1], 0.0))


def update_alpha(setup: Setup, agents: AgentState, log_prob: jax.Array,
                 ready: jax.Array) -> tuple[jax.Array, optax.OptState]:
    """Every ready temperature's step on RLkit's loss towards H̄ (`losses.alpha_loss`): (log_alpha, alpha_opt).

    log_prob float32[N, B]: log π_n(a|s) of the actions the actor loss drew, before the actor's step.
    """
    mask = ready.astype(jnp.float32)
    alpha_loss = jax.vmap(losses.alpha_loss, in_axes=(0, 0, None))
    loss = lambda log_alpha: jnp.sum(mask * alpha_loss(log_alpha, log_prob, setup.target_entropy))
    grads = jax.grad(loss)(agents.log_alpha)
    return _masked_step(setup.nets.alpha_tx, agents.log_alpha, grads, agents.alpha_opt, ready)


# ------------------------------------------------------------------- helpers

def _policy(setup: Setup, actor: Params, obs: jax.Array, noise: jax.Array) -> tuple[jax.Array, jax.Array]:
    """a ~ π_n(s) for every agent from standard-normal noise: obs [K, B, o], noise [K, B, a] -> ([K, B, a], [K, B])."""
    mean, log_std = jax.vmap(setup.nets.actor.apply)(actor, obs)
    squash = functools.partial(squashed_gaussian, tanh_log_prob=setup.config.ablations.tanh_log_prob)
    return jax.vmap(squash)(mean, log_std, noise)


def _min_q(setup: Setup, params: Params, obs: jax.Array, act: jax.Array) -> jax.Array:
    """Each slot's critic value, the min of its twin: leaves [K, ...], obs [K, B, o], act [K, B, a] -> [K, B]."""
    return jax.vmap(lambda p, o, a: jnp.min(setup.nets.critic.apply(p, o, a), axis=0))(params, obs, act)


def _masked_step(tx: optax.GradientTransformation, params: Params, grads: Params, opt_state: optax.OptState,
                 mask: jax.Array) -> tuple[Params, optax.OptState]:
    """One optimiser step of every agent (leaves [N, ...]), kept only where mask bool[N] is True."""

    def one(p, g, o, m):
        updates, new_opt = tx.update(g, o, p)
        new_params = optax.apply_updates(p, updates)
        keep = lambda new, old: jnp.where(m, new, old)
        return jax.tree.map(keep, new_params, p), jax.tree.map(keep, new_opt, o)

    return jax.vmap(one)(params, grads, opt_state, mask)


def _normal(keys: jax.Array, batch_size: int, action_size: int) -> jax.Array:
    """One standard-normal [B, a] per key: keys [K] -> [K, B, a]."""
    return jax.vmap(lambda k: jax.random.normal(k, (batch_size, action_size)))(keys)


def draw_noise(setup: Setup, key: jax.Array, batch_size: int) -> UpdateNoise:
    """The standard-normal draws of one update from `key` (see `UpdateNoise`)."""
    keys = jax.random.split(key, (setup.chain.num_agents, 2))
    k_next, k_pi = keys[:, 0], keys[:, 1]
    successor = (_normal(jax.vmap(lambda k: jax.random.fold_in(k, 1))(k_next[:-1]), batch_size, setup.action_size)
                 if setup.acting_next else jnp.zeros((0, batch_size, setup.action_size)))
    return UpdateNoise(next=_normal(k_next, batch_size, setup.action_size),
                       pi=_normal(k_pi, batch_size, setup.action_size), successor=successor)


def action_pulls(setup: Setup, agents: AgentState, batch: Transition, eta: jax.Array,
                 key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each critic's pull on agent n's actions: mean ‖∂(η Q̂_n)/∂a‖ and ‖∂((1 − η) Q̂_{n+1})/∂a‖, float32[N] each.

    A diagnostic of which critic drives the actor (computed once per epoch,
    with the running bounds as they stand, without updating them).
    """
    c, n = setup.chain, setup.chain.num_agents
    if not (c.cooperative or setup.config.ablations.normalise_last):
        zeros = jnp.zeros((n,))
        return zeros, zeros
    noise = _normal(jax.random.split(key, n), batch.obs.shape[1], setup.action_size)
    act, _ = _policy(setup, agents.actor, batch.obs, noise)
    slots = c.slot_params(agents.critic)

    def weighted(a):
        q_pair = c.pair(_min_q(setup, slots, c.slot_data(batch.obs), c.slot_data(a)))
        q_hat, _, scaled = normalised_pair(setup, q_pair, eta, agents.norm, jnp.zeros((n,), bool))
        # From the normaliser's bounds: already constants.
        units = losses.coop_units(setup.config.ablations.coop_scale, scaled.range_own, setup.config.ccp.norm_eps)[:, None]
        eta_used = scaled.eta_used[:, None]
        return (units * eta_used * q_hat[:, 0],
                units * jnp.where(c.has_next[:, None], 1 - eta_used, 0.0) * q_hat[:, 1])

    pulls = []
    for term in range(2):
        # q_hat's bounds are constants, so this is the gradient the actor loss sees from that term.
        g = jax.grad(lambda a: weighted(a)[term].sum())(act)
        pulls.append(jnp.linalg.norm(g, axis=-1).mean(-1))
    return pulls[0], pulls[1]


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
