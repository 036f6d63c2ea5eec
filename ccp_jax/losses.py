"""The loss terms of CSAC (SPEC §1) as pure functions on arrays.

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
    completed at s': its reward then stays 1 forever (SPEC §1), so the value is
    known exactly, `absorbing_value` = channel reward / (1 − γ).
    """
    soft = next_q - alpha * next_log_prob
    bootstrap = jnp.where(terminal > 0, 0.0, soft)
    return reward + gamma * jnp.where(completed > 0, absorbing_value, bootstrap)


def twin_q_loss(q: jax.Array, target: jax.Array) -> jax.Array:
    """Σ over the twin of mean squared error: q [2, B], target [B] -> scalar."""
    return jnp.sum(jnp.mean((q - jax.lax.stop_gradient(target)) ** 2, axis=-1))


def normalise(q: jax.Array, eps: float) -> jax.Array:
    """Q̂ = (Q − min_b Q) / (max_b Q − min_b Q + ε) over the batch, bounds held constant."""
    lo, hi = jax.lax.stop_gradient(jnp.min(q)), jax.lax.stop_gradient(jnp.max(q))
    return (q - lo) / (hi - lo + eps)


def coop_actor_loss(log_prob: jax.Array, q_own: jax.Array, q_next: jax.Array, eta: jax.Array,
                    alpha: jax.Array, eps: float) -> jax.Array:
    """CCP actor loss mean(α log π − [η Q̂_n + (1 − η) Q̂_{n+1}]); all inputs [B] but η, α."""
    coop = eta * normalise(q_own, eps) + (1.0 - eta) * normalise(q_next, eps)
    return jnp.mean(alpha * log_prob - coop)


def sac_actor_loss(log_prob: jax.Array, q: jax.Array, alpha: jax.Array) -> jax.Array:
    """Plain SAC actor loss mean(α log π − Q) on the agent's own critic."""
    return jnp.mean(alpha * log_prob - q)


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """RLkit's temperature loss −mean(log α · (log π + H̄)), log π held constant."""
    return -jnp.mean(log_alpha * jax.lax.stop_gradient(log_prob + target_entropy))


def q_range(q: jax.Array) -> jax.Array:
    """Ran(Q) over the batch: max_b Q − min_b Q."""
    return jnp.max(q) - jnp.min(q)


def eta_star(q_own: jax.Array, q_next: jax.Array, eps: float) -> jax.Array:
    """The ratio that recovers the sum Q_n + Q_{n+1}: Ran(Q_n) / (Ran(Q_n) + Ran(Q_{n+1}))."""
    r_own, r_next = q_range(q_own), q_range(q_next)
    return r_own / (r_own + r_next + eps)
