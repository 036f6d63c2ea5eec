"""Actor and critic networks (flax.linen), as in RLkit's SAC.

Shapes below are for one agent; the trainer stacks agents on a leading axis
by vmapping `init` and `apply`.
"""
from __future__ import annotations

import functools
import itertools
import math
import operator
from typing import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # RLkit's clamp


def rlkit_fanin_init(key: jax.Array, shape: Sequence[int], dtype=jnp.float32) -> jax.Array:
    """RLkit's `fanin_init` of a hidden layer: U(±1/√d), where d is the first dimension of the torch
    weight [out, in] — the layer's output size, not its fan-in. A flax kernel is [in, out]."""
    bound = 1.0 / math.sqrt(shape[-1])
    return jax.random.uniform(key, shape, dtype, -bound, bound)


def symmetric_uniform(scale: float) -> Callable:
    """U(±scale), RLkit's initialiser of a network's last layer (`init_w`)."""
    return lambda key, shape, dtype=jnp.float32: jax.random.uniform(key, shape, dtype, -scale, scale)


class ConcatDense(nn.Module):
    """`nn.Dense` applied to the concatenation of its inputs, computed part by part.

    inputs [..., d_i] -> [..., features], with one kernel [Σ d_i, features] and a bias,
    the parameters (and initial values) of `nn.Dense` on the concatenated input. Product by
    product, XLA can share a part common to two calls (the critic's obs, in its loss and in the
    actor's) and differentiate only through the parts that need it (the action columns).
    """

    features: int
    kernel_init: Callable = nn.linear.default_kernel_init

    @nn.compact
    def __call__(self, *inputs: jax.Array) -> jax.Array:
        sizes = [x.shape[-1] for x in inputs]
        kernel = self.param("kernel", self.kernel_init, (sum(sizes), self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        rows = [0, *itertools.accumulate(sizes)]
        return functools.reduce(operator.add, [x @ kernel[a:b] for x, a, b in zip(inputs, rows, rows[1:])]) + bias


class MLP(nn.Module):
    """MLP with a linear output layer; ReLU hidden layers unless a subclass sets `activation`.

    inputs [..., d_i] are read as their concatenation [..., Σ d_i] (`ConcatDense`).
    `init_scheme`: "flax" (lecun-normal kernels, zero biases) or "rlkit" (RLkit's: `rlkit_fanin_init`
    hidden kernels, an output kernel U(±`out_init_w`), zero biases), so the initial outputs are
    close to 0 everywhere: Q ≈ 0 and a policy of mean 0 and log-std 0 in every state.
    """

    hidden: Sequence[int]
    out: int
    activation: Callable[[jax.Array], jax.Array] = nn.relu
    init_scheme: str = "flax"
    out_init_w: float = 3e-3

    @nn.compact
    def __call__(self, *inputs: jax.Array) -> jax.Array:
        rlkit = self.init_scheme == "rlkit"
        hidden_init = rlkit_fanin_init if rlkit else nn.linear.default_kernel_init
        out_init = symmetric_uniform(self.out_init_w) if rlkit else nn.linear.default_kernel_init
        widths, inits = [*self.hidden, self.out], [hidden_init] * len(self.hidden) + [out_init]
        # Named as nn.Dense's auto-names, so parameter trees (and checkpoints) are those of plain Dense layers.
        x = ConcatDense(widths[0], inits[0], name="Dense_0")(*inputs)
        for i, (width, init) in enumerate(zip(widths[1:], inits[1:]), start=1):
            x = nn.Dense(width, kernel_init=init, name=f"Dense_{i}")(self.activation(x))
        return x


class Actor(nn.Module):
    """Tanh-Gaussian policy head: obs [..., obs_dim] -> (mean, log_std) [..., act_dim]."""

    hidden: Sequence[int]
    action_size: int
    init_scheme: str = "flax"

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        # RLkit's TanhGaussianPolicy draws both heads' kernels from U(±1e-3) (and the log-std bias too; ours is 0).
        out = MLP(self.hidden, 2 * self.action_size, init_scheme=self.init_scheme, out_init_w=1e-3)(obs)
        mean, log_std = jnp.split(out, 2, axis=-1)
        return mean, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)


class TwinCritic(nn.Module):
    """Two independent Q-networks: (obs [..., o], act [..., a]) -> q [2, ...]."""

    hidden: Sequence[int]
    init_scheme: str = "flax"

    @nn.compact
    def __call__(self, obs: jax.Array, act: jax.Array) -> jax.Array:
        twin = nn.vmap(MLP, variable_axes={"params": 0}, split_rngs={"params": True},
                       in_axes=None, out_axes=0, axis_size=2)
        return twin(self.hidden, 1, init_scheme=self.init_scheme)(obs, act)[..., 0]


def sample_action(mean: jax.Array, log_std: jax.Array, key: jax.Array,
                  tanh_log_prob: str) -> tuple[jax.Array, jax.Array]:
    """Reparameterised tanh-Gaussian sample and its log-probability, `squashed_gaussian` of fresh noise."""
    return squashed_gaussian(mean, log_std, jax.random.normal(key, mean.shape, mean.dtype), tanh_log_prob)


def squashed_gaussian(mean: jax.Array, log_std: jax.Array, noise: jax.Array,
                      tanh_log_prob: str) -> tuple[jax.Array, jax.Array]:
    """The tanh-Gaussian action for standard-normal `noise` and its log-probability.

    mean, log_std, noise: [..., a]. Returns action [..., a] in (-1, 1) and log_prob [...].
    `tanh_log_prob` picks the change-of-variables term log(1 − tanh(u)²):
    "rlkit" is RLkit's TanhNormal, log(1 − tanh(u)² + 1e-6), whose ε caps the
    term (and zeroes its gradient) once an action saturates (|u| ≳ 7); "exact"
    is the closed form, which keeps growing, 2|u| per saturated dimension.
    """
    u = mean + jnp.exp(log_std) * noise
    gauss = -0.5 * (((u - mean) / jnp.exp(log_std)) ** 2 + 2 * log_std + jnp.log(2 * jnp.pi))
    action = jnp.tanh(u)
    if tanh_log_prob == "rlkit":
        squash = jnp.log(1.0 - action**2 + 1e-6)
    else:
        # log(1 - tanh(u)^2) in a form that stays finite for large |u|.
        squash = 2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    return action, jnp.sum(gauss - squash, axis=-1)


def deterministic_action(mean: jax.Array) -> jax.Array:
    """The evaluation action: tanh of the Gaussian mean."""
    return jnp.tanh(mean)
