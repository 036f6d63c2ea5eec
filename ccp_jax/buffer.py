"""On-device replay buffers: one ring buffer per agent, stacked on a leading axis.

A transition goes to the buffer of the agent that acted, i.e. of the stage of
the state where the action was taken (docs/design.md#the-method; the paper's Algorithm 1).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from flax import struct


class Transition(NamedTuple):
    """One step (s, a, r[1..R], s', flags). Shapes for a single transition."""

    obs: jax.Array  # float32[obs]
    action: jax.Array  # float32[act]
    rewards: jax.Array  # float32[R]: one channel per agent (R = 1 for end-to-end SAC)
    next_obs: jax.Array  # float32[obs]
    terminal: jax.Array  # float32[]: the episode truly ended at s' (success or failure, not time)
    completed: jax.Array  # float32[R]: channel's subtask is done at s', so its value is absorbing
    next_stage: jax.Array  # int32[]: U(s'), which says whose policy acts at s'


class ReplayBuffer(struct.PyTreeNode):
    """`data` leaves are [num_agents, capacity, ...]; `ptr`/`size` are int32[num_agents]."""

    data: Transition
    ptr: jax.Array
    size: jax.Array

    @property
    def capacity(self) -> int:
        return self.data.obs.shape[-2]  # obs leaves are [..., capacity, obs], also under grid axes


def zero_transition(obs_size: int, action_size: int, num_channels: int) -> Transition:
    """A single all-zero transition of these sizes (the example `init_buffer` shapes buffers after)."""
    return Transition(obs=jnp.zeros((obs_size,)), action=jnp.zeros((action_size,)),
                      rewards=jnp.zeros((num_channels,)), next_obs=jnp.zeros((obs_size,)),
                      terminal=jnp.zeros(()), completed=jnp.zeros((num_channels,)),
                      next_stage=jnp.zeros((), jnp.int32))


def init_buffer(example: Transition, num_agents: int, capacity: int) -> ReplayBuffer:
    """Empty buffers shaped like `example` (a single, unbatched transition)."""
    data = jax.tree.map(lambda x: jnp.zeros((num_agents, capacity) + jnp.shape(x), jnp.result_type(x)), example)
    zeros = jnp.zeros((num_agents,), jnp.int32)
    return ReplayBuffer(data=data, ptr=zeros, size=zeros)


def add(buffer: ReplayBuffer, batch: Transition, agent: jax.Array) -> ReplayBuffer:
    """Writes E transitions (leaves [E, ...]) into the buffers of `agent` (int32[E]).

    Transitions routed to the same agent take consecutive slots in env order.
    """
    num_agents, capacity = buffer.ptr.shape[0], buffer.capacity
    onehot = (agent[:, None] == jnp.arange(num_agents)).astype(jnp.int32)  # [E, N]
    rank = jnp.take_along_axis(jnp.cumsum(onehot, 0) - onehot, agent[:, None], 1)[:, 0]
    slot = (buffer.ptr[agent] + rank) % capacity
    data = jax.tree.map(lambda d, x: d.at[agent, slot].set(x), buffer.data, batch)
    count = onehot.sum(0)
    return ReplayBuffer(data=data, ptr=(buffer.ptr + count) % capacity,
                        size=jnp.minimum(buffer.size + count, capacity))


def sample_indices(size: jax.Array, key: jax.Array, batch_size: int) -> jax.Array:
    """int32[N, B]: uniform slots of the filled part of each agent's buffer (`size` int32[N]; slot 0 if empty).

    Drawn apart from `gather` so that a loop over updates can draw all of its indices at once.
    """
    keys = jax.random.split(key, size.shape[0])
    return jax.vmap(lambda k, n: jax.random.randint(k, (batch_size,), 0, jnp.maximum(n, 1)))(keys, size)


def gather(buffer: ReplayBuffer, idx: jax.Array) -> Transition:
    """Agent n's transitions at slots idx[n] (int32[N, B]): leaves [N, B, ...]."""
    return jax.tree.map(lambda d: jax.vmap(lambda dn, i: dn[i])(d, idx), buffer.data)


def sample(buffer: ReplayBuffer, key: jax.Array, batch_size: int) -> Transition:
    """Uniform batches from the filled part of every agent's buffer: leaves [N, B, ...].

    An empty buffer yields its (zero) slot 0; callers mask such agents out with `ready`.
    """
    return gather(buffer, sample_indices(buffer.size, key, batch_size))


def ready(buffer: ReplayBuffer, batch_size: int) -> jax.Array:
    """bool[N]: agents whose buffer holds at least one batch of data."""
    return buffer.size >= batch_size
