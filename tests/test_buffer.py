"""Per-agent ring buffers: routing by stage, wrap-around, sampling only filled slots."""
import chex
import jax
import jax.numpy as jnp
import numpy as np

from ccp_jax import buffer as replay
from ccp_jax.buffer import Transition


def _batch(values, obs_size=2):
    v = jnp.asarray(values, jnp.float32)
    e = v.shape[0]
    return Transition(obs=jnp.repeat(v[:, None], obs_size, 1), action=v[:, None], rewards=jnp.stack([v, -v], 1),
                      next_obs=jnp.repeat(v[:, None] + 0.5, obs_size, 1), terminal=jnp.zeros(e),
                      completed=jnp.zeros((e, 2)), next_stage=jnp.zeros(e, jnp.int32))


def _empty(num_agents=3, capacity=4):
    return replay.init_buffer(jax.tree.map(lambda x: x[0], _batch([0.0])), num_agents, capacity)


def test_routing_by_stage_keeps_env_order():
    buf = replay.add(_empty(), _batch([1.0, 2.0, 3.0, 4.0]), jnp.array([0, 2, 0, 2]))
    chex.assert_shape(buf.data.obs, (3, 4, 2))
    np.testing.assert_array_equal(buf.size, [2, 0, 2])
    np.testing.assert_array_equal(buf.ptr, [2, 0, 2])
    np.testing.assert_array_equal(buf.data.action[0, :2, 0], [1.0, 3.0])
    np.testing.assert_array_equal(buf.data.action[2, :2, 0], [2.0, 4.0])
    np.testing.assert_array_equal(buf.data.rewards[2, 1], [4.0, -4.0])
    assert float(jnp.abs(buf.data.obs[1]).sum()) == 0.0  # nothing reached agent 1


def test_wrap_around_overwrites_oldest():
    buf = _empty(num_agents=1, capacity=4)
    add = jax.jit(replay.add)
    for start in range(0, 6, 2):
        buf = add(buf, _batch([start + 1.0, start + 2.0]), jnp.zeros(2, jnp.int32))
    # 6 writes into 4 slots: slots 0, 1 hold the 5th and 6th values.
    np.testing.assert_array_equal(buf.data.action[0, :, 0], [5.0, 6.0, 3.0, 4.0])
    assert int(buf.size[0]) == 4 and int(buf.ptr[0]) == 2


def test_sampling_only_filled_slots_and_readiness():
    buf = _empty(num_agents=2, capacity=64)
    buf = replay.add(buf, _batch(np.arange(1.0, 4.0)), jnp.zeros(3, jnp.int32))  # agent 0: 3 of 64 filled
    batch = replay.sample(buf, jax.random.PRNGKey(0), 256)
    chex.assert_shape(batch.obs, (2, 256, 2))
    assert set(np.asarray(batch.action[0, :, 0]).tolist()) == {1.0, 2.0, 3.0}
    np.testing.assert_array_equal(replay.ready(buf, 3), [True, False])
    np.testing.assert_array_equal(replay.ready(buf, 4), [False, False])


def test_zero_transition_shapes_buffers_and_capacity_holds_under_a_grid_axis():
    example = replay.zero_transition(obs_size=5, action_size=2, num_channels=3)
    chex.assert_shape([example.obs, example.action, example.rewards, example.terminal], [(5,), (2,), (3,), ()])
    assert example.next_stage.dtype == jnp.int32
    grid = jax.vmap(lambda _: replay.init_buffer(example, 4, 16))(jnp.arange(3))  # 3 runs, 4 agents, 16 slots
    chex.assert_shape(grid.data.next_obs, (3, 4, 16, 5))
    assert grid.capacity == 16 and replay.init_buffer(example, 4, 16).capacity == 16
