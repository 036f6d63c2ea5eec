"""envs_mjx.gym: Gymnasium views of contract envs step the JAX env exactly, pass gymnasium's checker, and the
vector env resets finished copies in the same step."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env  # noqa: E402

from envs_mjx.gym import GymEnv, GymVectorEnv, register  # noqa: E402
from envs_mjx.maze import Maze  # noqa: E402
from toy_env import Line  # noqa: E402


@pytest.mark.filterwarnings("ignore:.*infinity")  # an unbounded Box is the honest space of a generic env
@pytest.mark.parametrize("env", [Maze(rooms=3, episode_length=40), Line(stages=3)], ids=["maze", "user env"])
def test_gymnasium_checker_passes(env):
    check_env(GymEnv(env), skip_render_check=True)


def test_one_env_steps_the_jax_env_and_reports_stage_and_subtask_rewards():
    maze = Maze(rooms=2, episode_length=30)
    env = GymEnv(maze)
    obs, info = env.reset(seed=3)
    state = jax.jit(maze.reset)(jax.random.split(jax.random.key(3))[1])  # GymEnv's key use: split, use the second
    np.testing.assert_allclose(obs, state.obs)
    step = jax.jit(maze.step)  # as GymEnv steps it (eager and jitted steps differ by float rounding)
    rng = np.random.default_rng(0)
    for _ in range(30):
        action = rng.uniform(-1, 1, 2).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        state = step(state, jnp.asarray(action))
        np.testing.assert_allclose(obs, state.obs, rtol=1e-6)
        assert reward == pytest.approx(float(state.reward), rel=1e-6)
        assert info["stage"] == int(state.info["stage"])
        np.testing.assert_allclose(info["rewards"], state.info["rewards"], rtol=1e-6)
        assert info["rewards"].shape == (2,) and reward == pytest.approx(info["rewards"].sum(), rel=1e-5)
    assert truncated and not terminated  # the time limit ends it: not a termination


def test_success_terminates():
    env = GymEnv(Line(stages=2, episode_length=50))
    env.reset(seed=0)
    for _ in range(50):
        _, _, terminated, truncated, info = env.step(np.ones(1, np.float32))
        if terminated or truncated:
            break
    assert terminated and not truncated and info["success"] == 1.0 and info["stage"] == 1


def test_vector_env_resets_finished_copies_in_the_same_step():
    envs = GymVectorEnv(Line(stages=2, episode_length=6), num_envs=3)
    assert envs.observation_space.shape == (3, 3) and envs.action_space.shape == (3, 1)
    obs, info = envs.reset(seed=1)
    assert info["stage"].tolist() == [0, 0, 0]
    # Copy 0 runs to the goal (success: terminated), 1 stays (the 6-step limit: truncated), 2 backs off.
    actions = np.array([[1.0], [0.0], [-1.0]], np.float32)
    for t in range(6):
        obs, reward, terminated, truncated, info = envs.step(actions)
        if terminated[0]:
            break
    # x starts in [0, 0.2] and moves 0.25 a step: the goal (x >= 1.95) takes at most 8 steps, the limit 6.
    assert not terminated.any() and truncated.all()
    assert info["_final_obs"].all() and np.isfinite(info["final_obs"]).all()
    assert (obs[:, 0] <= 0.2).all() and (info["stage"] == 0).all()  # fresh episodes returned
    np.testing.assert_allclose(info["final_obs"][:, 0], info["final_obs"][:, 0].clip(-10, 10))
    assert info["final_info"]["stage"][0] == 1  # copy 0 had reached stage 2 (0-based 1) before the limit


def test_registered_tasks_make_through_gymnasium():
    register()
    register()  # idempotent
    env = gym.make("ccp/Maze3-v0", episode_length=20)
    obs, info = env.reset(seed=0)
    assert obs.shape == (24,) and info["rewards"].shape == (3,)
