"""The loss terms of CSAC (docs/design.md#the-method) as pure functions on arrays.

Everything here is for one agent and one batch of B samples; `learner.py`
assembles them over the stacked agents.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def soft_target(reward: jax.Array, next_q: jax.Array, next_log_prob: jax.Array, alpha: jax.Array,
                terminal: jax.Array, completed: jax.Array, gamma: float, absorbing_value: float) -> jax.Array:
    """Critic target y [B] = r + γ · bootstrap.

    reward, next_q (min of the target twin at s', a' ~ π_n(s')), next_log_prob,
    terminal, completed: [B]. The bootstrap is the soft value Q̄ − α log π,
    except after a true termination (0) and where the channel's subtask is
    completed at s': its reward then stays 1 forever (docs/design.md#decisions-the-paper-leaves-open), so the value is
    known exactly, `absorbing_value` = channel reward / (1 − γ).
    """
    soft = next_q - alpha * next_log_prob
    bootstrap = jnp.where(terminal > 0, 0.0, soft)
    return reward + gamma * jnp.where(completed > 0, absorbing_value, bootstrap)


def twin_q_loss(q: jax.Array, target: jax.Array) -> jax.Array:
    """Σ over the twin of mean squared error: q [2, B], target [B] -> scalar."""
    return jnp.sum(jnp.mean((q - jax.lax.stop_gradient(target)) ** 2, axis=-1))


def normalise(q: jax.Array, eps: float, lo: jax.Array | None = None, scale: jax.Array | None = None) -> jax.Array:
    """Q̂ = (Q − lo) / (scale + ε) with lo, scale held constant.

    By default lo and scale are the batch's min and range, the paper's
    normaliser: Q̂ = (Q − min_b Q) / (max_b Q − min_b Q + ε).
    """
    if lo is None:
        lo = jnp.min(q)
    if scale is None:
        scale = jnp.max(q) - lo
    return (q - jax.lax.stop_gradient(lo)) / (jax.lax.stop_gradient(scale) + eps)


def coop_actor_loss(log_prob: jax.Array, q_hat_own: jax.Array, q_hat_next: jax.Array, eta: jax.Array,
                    alpha: jax.Array, units: jax.Array | float = 1.0) -> jax.Array:
    """CCP actor loss mean(α log π − units · [η Q̂_n + (1 − η) Q̂_{n+1}]) on normalised critics; arrays [B].

    `units` (a held-constant scalar) expresses the cooperative objective in other units:
    1 is the paper's; the own critic's normaliser scale puts it in Q_n's units.
    """
    objective = jax.lax.stop_gradient(units) * (eta * q_hat_own + (1.0 - eta) * q_hat_next)
    return jnp.mean(alpha * log_prob - objective)


def sac_actor_loss(log_prob: jax.Array, q: jax.Array, alpha: jax.Array) -> jax.Array:
    """Plain SAC actor loss mean(α log π − Q) on the agent's own critic."""
    return jnp.mean(alpha * log_prob - q)


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """RLkit's temperature loss −mean(log α · (log π + H̄)), log π held constant."""
    return -jnp.mean(log_alpha * jax.lax.stop_gradient(log_prob + target_entropy))
