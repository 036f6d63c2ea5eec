"""The loss terms of CSAC as pure functions on arrays (docs/design.md#the-method).

Equation numbers are the paper's (Erskine & Lehnert, RA-L 2022). Unless a
docstring says otherwise, everything here is for one agent and one batch of
B samples; `learner.py` maps it over the stacked agents.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ccp_jax.config import CoopScale, Normaliser


# ------------------------------------------------------------------ critic

def soft_target(reward: jax.Array, next_q: jax.Array, next_log_prob: jax.Array, alpha: jax.Array,
                terminal: jax.Array, completed: jax.Array, gamma: float, absorbing_value: float) -> jax.Array:
    """Critic target y [B] = r + γ · bootstrap (Algorithm 2's y, the target of Eq. (1)).

    reward, next_q (min of the target twin at s', a' ~ π_n(s')), next_log_prob,
    terminal, completed: [B]. The bootstrap is the soft value Q̄ − α log π,
    except after a true termination (0) and where the channel's subtask is
    completed at s': its reward then stays 1 forever (Eq. (5)), so the value is
    known exactly, `absorbing_value` = channel reward / (1 − γ)
    (docs/design.md#decisions-the-paper-leaves-open: success and completed stages are absorbing).
    """
    soft = next_q - alpha * next_log_prob
    bootstrap = jnp.where(terminal > 0, 0.0, soft)
    return reward + gamma * jnp.where(completed > 0, absorbing_value, bootstrap)


def twin_q_loss(q: jax.Array, target: jax.Array) -> jax.Array:
    """Eq. (1) summed over the twin: Σ_i mean_b (Q_i(s, a) − y)²; q [2, B], target [B] -> scalar."""
    return jnp.sum(jnp.mean((q - jax.lax.stop_gradient(target)) ** 2, axis=-1))


# -------------------------------------------------------------- normaliser

def normalise(q: jax.Array, eps: float, lo: jax.Array | None = None, scale: jax.Array | None = None) -> jax.Array:
    """Q̂ = (Q − lo) / (scale + ε) with lo, scale held constant; q [..., B], lo and scale broadcast against it.

    By default lo and scale are the batch's min and range, the paper's
    normaliser (Eq. (4)): Q̂ = (Q − min_b Q) / (max_b Q − min_b Q + ε).
    """
    if lo is None:
        lo = jnp.min(q)
    if scale is None:
        scale = jnp.max(q) - lo
    return (q - jax.lax.stop_gradient(lo)) / (jax.lax.stop_gradient(scale) + eps)


class Normalised(NamedTuple):
    """`normalise_batch`'s result; for critic values [..., B], the bounds are [...]."""

    q_hat: jax.Array  # [..., B]
    scale: jax.Array  # what Q − lo was divided by (before ε): Ran(Q) as the normaliser sees it
    batch_range: jax.Array  # max_b Q − min_b Q
    running_lo: jax.Array  # the running (EMA) bounds after this batch
    running_hi: jax.Array


def normalise_batch(q: jax.Array, running_lo: jax.Array, running_hi: jax.Array, kind: Normaliser, eps: float,
                    ema_rate: float, floor: float) -> Normalised:
    """Q̂ of critic values q [..., B] (one batch along the last axis) under the normaliser `kind`.

    "batch" is the paper's Eq. (4): Q̂ = (Q − min_b Q) / (max_b Q − min_b Q + ε). The others are choices
    the paper leaves open (docs/design.md#decisions-the-paper-leaves-open): "ema" divides by the running
    range instead, so a critic that is still flat is not blown up to full scale; "floor" by the batch range
    but at least `floor` (reward units); "none" leaves Q as it is. The bounds are held constant.

    running_lo, running_hi [...]: the EMA bounds before this batch; they move towards the batch's min and
    max at `ema_rate` whatever `kind` is (η* of "auto" reads them).
    """
    bounds = jax.lax.stop_gradient(q)
    b_lo, b_hi = bounds.min(-1), bounds.max(-1)
    e_lo = running_lo + ema_rate * (b_lo - running_lo)
    e_hi = running_hi + ema_rate * (b_hi - running_hi)
    if kind == "ema":
        lo, scale = e_lo, e_hi - e_lo
    elif kind == "floor":
        lo, scale = b_lo, jnp.maximum(b_hi - b_lo, floor)
    elif kind == "none":
        lo, scale = jnp.zeros_like(b_lo), jnp.ones_like(b_hi)
    else:
        lo, scale = b_lo, b_hi - b_lo
    q_hat = normalise(q, eps, lo[..., None], scale[..., None])
    return Normalised(q_hat=q_hat, scale=scale, batch_range=b_hi - b_lo, running_lo=e_lo, running_hi=e_hi)


# ------------------------------------------------------------------- actor

def coop_objective(q_hat_own: jax.Array, q_hat_next: jax.Array, eta: jax.Array) -> jax.Array:
    """The cooperative objective C(Q_n, Q_{n+1}) = η Q̂_n + (1 − η) Q̂_{n+1} of Eq. (3); arrays [B], eta scalar."""
    return eta * q_hat_own + (1.0 - eta) * q_hat_next


def coop_units(coop_scale: CoopScale, own_scale: jax.Array, eps: float) -> jax.Array:
    """The factor on C_n in the actor loss, shaped as `own_scale` (the own critic's normaliser scale, [N]).

    "unit" is the paper's (C_n ∈ [0, 1]); "own" undoes the own critic's scaling, so that η = 1 is Naive's
    actor loss and α weighs entropy against values in Q_n's units (docs/design.md#decisions-the-paper-leaves-open).
    """
    return own_scale + eps if coop_scale == "own" else jnp.ones(own_scale.shape)


def coop_actor_loss(log_prob: jax.Array, q_hat_own: jax.Array, q_hat_next: jax.Array, eta: jax.Array,
                    alpha: jax.Array, units: jax.Array | float = 1.0) -> jax.Array:
    """CCP actor loss mean(α log π − units · C) on normalised critics; arrays [B], the rest scalars.

    Eq. (2) with SAC's entropy term, as Algorithm 2 writes it, and C of Eq. (3). `units` (held constant)
    expresses the objective in other units: 1 is the paper's; `coop_units` gives Q_n's.
    """
    objective = jax.lax.stop_gradient(units) * coop_objective(q_hat_own, q_hat_next, eta)
    return jnp.mean(alpha * log_prob - objective)


def sac_actor_loss(log_prob: jax.Array, q: jax.Array, alpha: jax.Array) -> jax.Array:
    """Plain SAC actor loss mean(α log π − Q) on the agent's own critic; arrays [B], alpha scalar."""
    return jnp.mean(alpha * log_prob - q)


# ------------------------------------------------------------- temperature

def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """RLkit's temperature loss −mean(log α · (log π + H̄)), log π [B] held constant, log_alpha scalar."""
    return -jnp.mean(log_alpha * jax.lax.stop_gradient(log_prob + target_entropy))
