"""experiments/peg_insertion_only.py: the peg's insertion alone, each episode from a scripted thick grasp."""
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

from envs_mjx.contract import check_env  # noqa: E402
from envs_mjx.peg_in_hole import scripted_action  # noqa: E402
from peg_insertion_only import InsertionOnly  # noqa: E402

B, T = 4, 60


@pytest.fixture(scope="module")
def env():
    return InsertionOnly(episode_length=T)


@pytest.fixture(scope="module")
def starts(env):
    return jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(3), B))


def _rollout(env, starts, act):
    """(success, done, truncation), each float32[B, T], of T steps of `act(state, key)` from `starts`."""
    def one(s0, key):
        def body(s, k):
            s = env.step(s, act(s, k))
            return s, (s.metrics["success"], s.done, s.info["truncation"])
        return jax.lax.scan(body, s0, jax.random.split(key, T))[1]
    return [np.asarray(x) for x in jax.jit(jax.vmap(one))(starts, jax.random.split(jax.random.PRNGKey(4), B))]


def test_every_episode_starts_in_the_insertion_stage_holding_the_thick_section(starts):
    np.testing.assert_array_equal(starts.metrics["start_grasped"], 1.0)
    np.testing.assert_array_equal(starts.pipeline_state.metrics["grasp_thick"], 1.0)  # the grasp that can insert
    np.testing.assert_array_equal(starts.info["stage"], 1)
    np.testing.assert_array_equal(starts.info["steps"], 0)
    np.testing.assert_array_equal(starts.info["rewards"][:, 0], 1.0)  # the grasp stage is done
    assert starts.info["rewards"].shape == (B, 2) and starts.obs.shape == (B, 41)


def test_pushing_on_inserts_and_letting_go_does_not(env, starts):
    success, done, truncation = _rollout(env, starts, lambda s, k: scripted_action(s.pipeline_state, jnp.int32(0), k))
    first = success.argmax(1)
    assert success.any(1).all(), "the scripted push from the grasp must insert every peg"
    np.testing.assert_array_equal(done[np.arange(B), first], 1.0)
    np.testing.assert_array_equal(truncation[np.arange(B), first], 0.0)
    success, done, truncation = _rollout(env, starts, lambda s, k: jnp.array([0.0, -1.0]))  # open and stay
    assert not success.any()
    np.testing.assert_array_equal(done[:, -1], 1.0)  # the episode's own length ends it, as a truncation
    np.testing.assert_array_equal(truncation[:, -1], 1.0)
    assert not done[:, :-1].any()


def test_meets_the_contract(env):
    check_env(env, num_envs=B, steps=T)
