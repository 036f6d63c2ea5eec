"""Networks of the transition policies and proximity predictors, and a running observation normaliser.

Shapes are for one transition policy / predictor; the K = N − 1 of them (one
per primitive 1..N−1, indexed k − 1) are stacked on a leading axis by vmapping
`init`, like the SAC agents.
"""
from __future__ import annotations

from typing import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from ccp_jax.networks import MLP

OBS_CLIP = 5.0  # normalised observations are clipped to ±5, as in the released code


class TanhMLP(MLP):
    """tanh MLP with a linear output layer (the released PPO policy and value nets)."""

    activation: Callable[[jax.Array], jax.Array] = jnp.tanh


class TransitionPolicy(nn.Module):
    """obs [..., o] -> (mean [..., a], log_std [..., a], terminate logits [..., 2]).

    A Gaussian action (state-independent log-std, initialised to 0) and a 2-way
    categorical "terminate" head on one tanh trunk.
    """

    hidden: Sequence[int]
    action_size: int

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        out = TanhMLP(self.hidden, self.action_size + 2)(obs)
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_size,))
        mean, logits = out[..., : self.action_size], out[..., self.action_size:]
        return mean, jnp.broadcast_to(log_std, mean.shape), logits


class Value(nn.Module):
    """obs [..., o] -> V [...]."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return TanhMLP(self.hidden, 1)(obs)[..., 0]


class Proximity(nn.Module):
    """obs [..., o] -> raw proximity [...] (linear output; clipped to [0, 1] where it is used as a reward)."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return MLP(self.hidden, 1)(obs)[..., 0]


class RunningNorm(struct.PyTreeNode):
    """Running mean and variance of observations: mean, var float32[o], count float32[]."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array


def norm_init(obs_size: int) -> RunningNorm:
    # A tiny prior count (as baselines' RunningMeanStd) keeps the first merge well defined.
    return RunningNorm(mean=jnp.zeros((obs_size,)), var=jnp.ones((obs_size,)), count=jnp.float32(1e-4))


def norm_update(stats: RunningNorm, x: jax.Array, weight: jax.Array) -> RunningNorm:
    """Merges the rows of x [B, o] with weight [B] (0/1 masks) into the running moments (Chan et al.)."""
    n = weight.sum()
    safe = jnp.maximum(n, 1.0)
    mean_b = (weight[:, None] * x).sum(0) / safe
    var_b = (weight[:, None] * (x - mean_b) ** 2).sum(0) / safe
    total = stats.count + n
    delta = mean_b - stats.mean
    mean = stats.mean + delta * n / total
    m2 = stats.var * stats.count + var_b * n + delta ** 2 * stats.count * n / total
    return RunningNorm(mean=mean, var=m2 / total, count=total)


def normalise(stats: RunningNorm, x: jax.Array) -> jax.Array:
    """(x − mean) / std, clipped to ±OBS_CLIP; x [..., o]."""
    return jnp.clip((x - stats.mean) / jnp.sqrt(stats.var + 1e-8), -OBS_CLIP, OBS_CLIP)


def gaussian_log_prob(mean: jax.Array, log_std: jax.Array, x: jax.Array) -> jax.Array:
    """log N(x; mean, exp(log_std)) summed over the last axis: [..., a] -> [...]."""
    z = (x - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def gaussian_entropy(log_std: jax.Array) -> jax.Array:
    return jnp.sum(log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e), axis=-1)


def categorical_log_prob(logits: jax.Array, choice: jax.Array) -> jax.Array:
    """log p(choice) of a categorical; logits [..., 2], choice int/float [...] in {0, 1}."""
    logp = jax.nn.log_softmax(logits)
    return jnp.take_along_axis(logp, choice.astype(jnp.int32)[..., None], axis=-1)[..., 0]


def categorical_entropy(logits: jax.Array) -> jax.Array:
    logp = jax.nn.log_softmax(logits)
    return -jnp.sum(jnp.exp(logp) * logp, axis=-1)
