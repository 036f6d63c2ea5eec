"""PPO for the transition policies: GAE over transition steps, the clipped loss, the epoch's update.

A transition sample is one step at which a transition policy acted: either it
moved (a Gaussian action, env step taken) or it terminated (hand-over to the
primitive; its action is ignored). Its log-probability is the action's
(unless it terminated) plus the termination head's (unless termination was
forced by the step limit, which the policy did not choose).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from ccp_jax.config import Config
from ccp_jax.tp.networks import (RunningNorm, TransitionPolicy, Value, categorical_entropy, categorical_log_prob,
                                 gaussian_entropy, gaussian_log_prob, normalise)


class Samples(NamedTuple):
    """Transition samples of a rollout, leaves [T, E, ...] (or flattened [M, ...])."""

    obs: jax.Array  # float32[..., o]: the state where the transition policy acted
    policy: jax.Array  # int32: transition policy k − 1 that acted (leads into primitive k)
    action: jax.Array  # float32[..., a]: the unclipped Gaussian sample
    term: jax.Array  # float32: 1 = terminated here (hand-over; no transition step taken)
    forced: jax.Array  # float32: 1 = termination forced by the step limit
    reward: jax.Array  # float32: proximity increase (+ terminal proximity on the segment's last sample)
    end: jax.Array  # float32: the segment ended at this sample (terminated, episode over, or subtask done)
    valid: jax.Array  # float32: a transition policy acted at this step (primitive steps are 0)


def log_prob(mean, log_std, logits, action, term, forced) -> jax.Array:
    """log π(action, term | s) of samples: the action counts unless terminating, the head unless forced."""
    return ((1.0 - term) * gaussian_log_prob(mean, log_std, action)
            + (1.0 - forced) * categorical_log_prob(logits, term))


def gae(reward, value, end, valid, last_value, gamma: float, lam: float) -> tuple[jax.Array, jax.Array]:
    """Advantages and returns over transition steps only: all [T, E] -> ([T, E], [T, E]).

    Primitive steps (valid 0) are skipped: they pass the carry through. A
    segment's last sample (end 1) is terminal; a segment still running at the
    rollout's end bootstraps from last_value [E] (the value of the final state).
    """
    def back(carry, x):
        adv_next, v_next = carry
        r, v, e, ok = x
        delta = r + gamma * (1.0 - e) * v_next - v
        adv = delta + gamma * lam * (1.0 - e) * adv_next
        keep = ok > 0
        return (jnp.where(keep, adv, adv_next), jnp.where(keep, v, v_next)), adv

    _, adv = jax.lax.scan(back, (jnp.zeros_like(last_value), last_value), (reward, value, end, valid), reverse=True)
    adv = adv * valid
    return adv, (adv + value) * valid


class PPOMetrics(NamedTuple):
    pi_loss: jax.Array
    v_loss: jax.Array
    entropy: jax.Array
    approx_kl: jax.Array
    clip_frac: jax.Array


def make_ppo_update(config: Config, policy: TransitionPolicy, value: Value, tx: optax.GradientTransformation):
    """`update(params, opt_state, stats, samples, logp_old, adv, ret, weight, key) -> (params, opt_state, metrics)`.

    ONE transition policy (params = (policy params, value params)) on the
    flattened samples [M] of the epoch, of which `weight` [M] selects its own.
    `tp_ppo_epochs` passes over them in minibatches of `tp_minibatch`; the
    selected samples are shuffled to the front each pass, and minibatches past
    them are skipped (params and optimiser state kept), so the number of
    updates follows the data while shapes stay static.
    """
    mb, clip_eps = config.tp.tp_minibatch, config.tp.tp_clip

    def loss_fn(params, stats: RunningNorm, batch: Samples, logp_old, adv, ret, w):
        obs = normalise(stats, batch.obs)
        mean, log_std, logits = policy.apply(params[0], obs)
        logp = log_prob(mean, log_std, logits, batch.action, batch.term, batch.forced)
        ratio = jnp.exp(logp - logp_old)
        pg = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * adv)
        entropy = gaussian_entropy(log_std) + categorical_entropy(logits)
        v_loss = (value.apply(params[1], obs) - ret) ** 2
        wmean = lambda x: (w * x).sum() / jnp.maximum(w.sum(), 1.0)
        loss = wmean(pg) + config.tp.tp_value_coef * wmean(v_loss) - config.tp.tp_entropy_coef * wmean(entropy)
        return loss, PPOMetrics(wmean(pg), wmean(v_loss), wmean(entropy), wmean(logp_old - logp),
                                wmean((jnp.abs(ratio - 1.0) > clip_eps).astype(jnp.float32)))

    def update(params, opt_state, stats, samples: Samples, logp_old, adv, ret, weight, key):
        m = weight.shape[0]
        n_valid = weight.sum()
        num_mb = -(-m // mb)
        mean_a = (weight * adv).sum() / jnp.maximum(n_valid, 1.0)
        std_a = jnp.sqrt((weight * (adv - mean_a) ** 2).sum() / jnp.maximum(n_valid, 1.0))
        adv = (adv - mean_a) / (std_a + 1e-8)  # normalised over this policy's samples

        def minibatch(carry, j):
            params, opt_state, order = carry
            idx = jax.lax.dynamic_slice(order, (j * mb,), (mb,))
            w = weight[idx] * ((j * mb + jnp.arange(mb)) < n_valid)
            take = lambda x: x[idx]
            (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(
                params, stats, jax.tree.map(take, samples), logp_old[idx], adv[idx], ret[idx], w)
            updates, new_opt = tx.update(grads, opt_state, params)
            new_params = optax.apply_updates(params, updates)
            live = w.sum() > 0
            keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(live, a, b), new, old)
            return (keep(new_params, params), keep(new_opt, opt_state), order), (metrics, live)

        def epoch(carry, k):
            params, opt_state = carry
            # This policy's samples first, in random order; the rest (weight 0) after them.
            order = jnp.argsort(jnp.where(weight > 0, jax.random.uniform(k, (m,)), 2.0))
            order = jnp.concatenate([order, jnp.zeros((num_mb * mb - m,), order.dtype)])
            (params, opt_state, _), out = jax.lax.scan(minibatch, (params, opt_state, order), jnp.arange(num_mb))
            return (params, opt_state), out

        (params, opt_state), (metrics, live) = jax.lax.scan(
            epoch, (params, opt_state), jax.random.split(key, config.tp.tp_ppo_epochs))
        live = live.astype(jnp.float32)
        metrics = jax.tree.map(lambda x: (x * live).sum() / jnp.maximum(live.sum(), 1.0), metrics)
        return params, opt_state, metrics

    return update
