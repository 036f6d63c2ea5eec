"""Proximity predictors: targets, on-device success/failure buffers, loss and update.

Predictor k scores how close a state is to the initiation set of primitive
k + 1 (the set from which it succeeds). It regresses, per sample, onto
δ^(T−t) for the states s_0..s_T of a transition that handed over at s_T to a
primitive that then succeeded, and onto 0 for every state of a transition
whose primitive failed (or that never handed over).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from ccp_jax.tp.networks import Proximity, RunningNorm, normalise


def proximity_targets(length: jax.Array, success: jax.Array, max_len: int, delta: float) -> jax.Array:
    """Labels of segments stored as rows 0..length−1: δ^(length−1−t) if `success`, else 0.

    length int32[E], success bool[E] -> float32[E, max_len]; rows at or past `length` are 0.
    """
    t = jnp.arange(max_len)
    steps_to_go = (length[:, None] - 1 - t).astype(jnp.float32)
    label = jnp.where(success[:, None], delta ** steps_to_go, 0.0)
    return jnp.where(t < length[:, None], label, 0.0)


class SegmentBuffer(struct.PyTreeNode):
    """K ring buffers of labelled states: obs [K, C, o], label [K, C]; ptr, size int32[K]."""

    obs: jax.Array
    label: jax.Array
    ptr: jax.Array
    size: jax.Array


def buffer_init(num: int, capacity: int, obs_size: int) -> SegmentBuffer:
    zeros = jnp.zeros((num,), jnp.int32)
    return SegmentBuffer(obs=jnp.zeros((num, capacity, obs_size)), label=jnp.zeros((num, capacity)),
                         ptr=zeros, size=zeros)


def buffer_add(buf: SegmentBuffer, obs: jax.Array, label: jax.Array, slot: jax.Array,
               count: jax.Array) -> SegmentBuffer:
    """Writes rows 0..count[e]−1 of each env's segment into buffer slot[e].

    obs [E, L, o], label [E, L], slot int32[E], count int32[E] (0: nothing).
    Segments bound for the same buffer take consecutive places in env order.
    Rows not written are scattered out of bounds and dropped, so the cost does
    not depend on how many envs write (no data-dependent branch, which vmap
    would turn into a copy of the whole buffer).
    """
    num, capacity = buf.ptr.shape[0], buf.obs.shape[1]
    length = obs.shape[1]
    onehot = (slot[:, None] == jnp.arange(num)) * count[:, None]  # [E, K]
    offset = jnp.take_along_axis(jnp.cumsum(onehot, 0) - onehot, slot[:, None], 1)[:, 0]
    t = jnp.arange(length)
    pos = (buf.ptr[slot][:, None] + offset[:, None] + t) % capacity
    pos = jnp.where(t < count[:, None], pos, capacity)  # out of bounds: dropped
    k = jnp.broadcast_to(slot[:, None], pos.shape)
    added = onehot.sum(0)
    return SegmentBuffer(obs=buf.obs.at[k, pos].set(obs, mode="drop"),
                         label=buf.label.at[k, pos].set(label, mode="drop"),
                         ptr=(buf.ptr + added) % capacity, size=jnp.minimum(buf.size + added, capacity))


def buffer_sample(buf: SegmentBuffer, key: jax.Array, n: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """n uniform rows of every buffer: obs [K, n, o], label [K, n], weight [K, n] (0 where the buffer is empty)."""
    keys = jax.random.split(key, buf.ptr.shape[0])
    idx = jax.vmap(lambda k, s: jax.random.randint(k, (n,), 0, jnp.maximum(s, 1)))(keys, buf.size)
    take = lambda d: jax.vmap(lambda dk, i: dk[i])(d, idx)
    weight = jnp.broadcast_to((buf.size > 0)[:, None], idx.shape).astype(jnp.float32)
    return take(buf.obs), take(buf.label), weight


class ProximityData(struct.PyTreeNode):
    """The predictors' data: online successes (labels δ^(T−t)), failures (0), permanent successes (1)."""

    success: SegmentBuffer
    failure: SegmentBuffer
    permanent: SegmentBuffer


def proximity_loss(p_success: jax.Array, y_success: jax.Array, w_success: jax.Array,
                   p_failure: jax.Array, w_failure: jax.Array) -> jax.Array:
    """Least squares, per sample: mean_w (P(s_succ) − y)² + mean_w P(s_fail)²; all inputs [B].

    Each success state is pulled toward its own label (the released code
    broadcast [B, 1] − [B], pulling every state toward the batch's mean label).
    """
    wmean = lambda x, w: (w * x).sum() / jnp.maximum(w.sum(), 1.0)
    return wmean((p_success - y_success) ** 2, w_success) + wmean(p_failure ** 2, w_failure)


class PredictorMetrics(NamedTuple):
    loss: jax.Array
    success_mean: jax.Array  # mean P on the success batches (target: labels)
    failure_mean: jax.Array  # mean P on the failure batches (target: 0)


def make_predictor_update(net: Proximity, tx: optax.GradientTransformation, batch: int):
    """`update(params, opt_state, stats, data, key) -> (params, opt_state, metrics)`: one Adam step of every predictor.

    Leaves of params, opt_state, stats and metrics have the leading K axis.
    Each predictor's batch is `batch` failure states and `batch` success
    states, half online and half permanent; an empty buffer gets weight 0, so
    the other half (or a lone failure term) carries the loss.
    """
    half = batch // 2
    wmean = lambda x, w: (w * x).sum() / jnp.maximum(w.sum(), 1.0)

    def loss_fn(params, stats: RunningNorm, succ_obs, succ_y, succ_w, fail_obs, fail_w):
        p_s = net.apply(params, normalise(stats, succ_obs))
        p_f = net.apply(params, normalise(stats, fail_obs))
        loss = proximity_loss(p_s, succ_y, succ_w, p_f, fail_w)
        return loss, PredictorMetrics(loss, wmean(p_s, succ_w), wmean(p_f, fail_w))

    def one(params, opt_state, stats, succ_obs, succ_y, succ_w, fail_obs, fail_w):
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, stats, succ_obs, succ_y, succ_w, fail_obs, fail_w)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, metrics

    def update(params, opt_state, stats: RunningNorm, data: ProximityData, key: jax.Array):
        k_on, k_perm, k_fail = jax.random.split(key, 3)
        on_obs, on_y, on_w = buffer_sample(data.success, k_on, half)
        pm_obs, pm_y, pm_w = buffer_sample(data.permanent, k_perm, batch - half)
        fail_obs, _, fail_w = buffer_sample(data.failure, k_fail, batch)
        cat = lambda a, b: jnp.concatenate([a, b], axis=1)
        return jax.vmap(one)(params, opt_state, stats, cat(on_obs, pm_obs), cat(on_y, pm_y), cat(on_w, pm_w),
                             fail_obs, fail_w)

    return update


def clip_each_by_norm(max_norm: float) -> optax.GradientTransformation:
    """Clips every parameter's gradient to norm `max_norm` on its own (TF's clip_by_norm per variable)."""
    def clip(updates, params=None):
        del params
        def one(g):
            norm = jnp.sqrt(jnp.sum(g ** 2))
            return g * jnp.minimum(1.0, max_norm / jnp.maximum(norm, 1e-12))
        return jax.tree.map(one, updates)
    return optax.stateless(clip)
