"""The env contract checker, the StageWrapper, brax's pusher as a two-stage task, and user envs."""
from __future__ import annotations

import importlib.util
import json
import re
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import State

from envs_mjx.contract import EnvContractError, check_env, violations
from envs_mjx.stage_wrapper import StageSpec, StageWrapper
from toy_env import Line
from user_env_module import SPEC, Slider, make

# ---------------------------------------------------------------- check_env accepts conforming envs


def test_accepts_toy_line():
    check_env(Line())
    check_env(Line(stages=3, episode_length=5))  # episodes end (and are reset) inside the check


def test_accepts_maze():
    from envs_mjx.maze import Maze

    check_env(Maze(rooms=3), steps=30)


def test_accepts_user_stage_wrapper():
    check_env(make())


@pytest.mark.slow  # 30 s cold on a quiet 2-core CPU, ~70 s under load; test_peg covers peg in the default suite
def test_accepts_peg():
    if importlib.util.find_spec("envs_mjx.peg_in_hole") is None:
        pytest.skip("envs_mjx/peg_in_hole.py is absent")
    try:
        from envs_mjx.peg_in_hole import PegInHole
    except Exception as err:  # another engineer's work in progress
        pytest.skip(f"envs_mjx.peg_in_hole does not import: {err}")
    check_env(PegInHole(episode_length=20), num_envs=2, steps=25)


# ---------------------------------------------------------------- check_env rejects each broken rule


class Broken(Line):
    """`Line` with `fix(state, stepped)` applied to what reset (stepped=False) and step return."""

    def __init__(self, fix: Callable[[State, bool], State], **kw):
        super().__init__(**kw)
        self._fix = fix

    def reset(self, rng):
        return self._fix(super().reset(rng), False)

    def step(self, state, action):
        return self._fix(super().step(state, action), True)


def _info(state: State, **changes) -> State:
    return state.replace(info={**state.info, **changes})


def _drop_stage(s, stepped):
    return s.replace(info={k: v for k, v in s.info.items() if k != "stage"})


def _three_rewards(s, stepped):
    r = jnp.concatenate([s.info["rewards"], jnp.zeros((1,), jnp.float32)])
    return _info(s, rewards=r)


def _float_stage(s, stepped):
    return _info(s, stage=s.info["stage"].astype(jnp.float32))


def _flip_stage(s, stepped):
    """Stage 1 on odd steps, 0 on even ones, with rewards that agree with it: only the monotonicity breaks."""
    if not stepped:
        return s
    stage = (s.info["steps"] % 2).astype(jnp.int32)
    rewards = Line()._rewards(s.pipeline_state, stage)
    return _info(s, stage=stage, rewards=rewards).replace(reward=rewards.sum())


def _stretched_progress(s, stepped):
    """The current stage's reward spread over [-0.5, 1.5]; completed and future stages stay 1 and 0."""
    r, n = s.info["rewards"], jnp.arange(2)
    r = jnp.where(n == s.info["stage"], 2.0 * r - 0.5, r)
    return _info(s, rewards=r).replace(reward=r.sum())


def _reward_plus_half(s, stepped):
    return s.replace(reward=s.reward + 0.5)


def _nan_obs(s, stepped):
    return s.replace(obs=s.obs.at[-1].set(jnp.nan))


def _extra_key_after_step(s, stepped):
    return _info(s, extra=jnp.float32(0)) if stepped else s


def _truncation_without_done(s, stepped):
    return _info(s, truncation=jnp.float32(1)) if stepped else s


def _int_done(s, stepped):
    return s.replace(done=s.done.astype(jnp.int32))


BROKEN = {
    "missing key": (_drop_stage, "missing info['stage']"),
    "wrong shape": (_three_rewards, "info['rewards'] has shape (3,), expected (num_stages,)=(2,)"),
    "wrong dtype int": (_float_stage, "info['stage'] has dtype float32, expected int32"),
    "wrong dtype float": (_int_done, "done has dtype int32, expected float32"),
    "stage decreasing": (_flip_stage, "stage decreased"),
    "rewards outside [0, 1]": (_stretched_progress, "rewards outside [0, 1]"),
    "reward != sum": (_reward_plus_half, "reward != sum(info['rewards'])"),
    "obs not finite": (_nan_obs, "obs not finite"),
    "structure mismatch": (_extra_key_after_step, "reset/step pytree structure mismatch"),
    "truncation without done": (_truncation_without_done, "truncation without done"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_rejects_broken_rule(case):
    fix, rule = BROKEN[case]
    env = Broken(fix)
    problems = violations(env, steps=20)
    assert len(problems) == 1 and problems[0].startswith(rule), problems
    with pytest.raises(EnvContractError, match=re.escape(rule)) as err:
        check_env(env, steps=20)
    assert isinstance(err.value, ValueError) and err.value.problems == problems


def test_checks_one_whole_episode_by_default():
    """A check of 50 steps passed an env whose observations turn NaN at step 70 of its 100-step episodes."""
    from user_env_module import make_late_nan

    assert violations(make_late_nan(), steps=50) == []
    (problem,) = violations(make_late_nan())
    assert problem.startswith("obs not finite (step 70, env 0: [nan")


def test_rejects_missing_sizes():
    class NoSizes:
        def reset(self, rng):  # pragma: no cover - never reached
            raise AssertionError

    problems = violations(NoSizes())
    assert problems == ["missing num_stages", "missing observation_size", "missing action_size"]


def test_lists_every_broken_rule_at_once():
    def two(s, stepped):
        return _reward_plus_half(_nan_obs(s, stepped), stepped)

    problems = violations(Broken(two), steps=5)
    assert [p.split(" (")[0] for p in problems] == ["obs not finite", "reward != sum(info['rewards'])"]


# ---------------------------------------------------------------- StageWrapper


def _rollout(env, actions, key=jax.random.PRNGKey(0)):
    """reset + scan of `actions` [T, A] on one env; returns the reset State and the stacked step States."""
    def run(key):
        s0 = env.reset(key)
        return s0, jax.lax.scan(lambda s, a: (env.step(s, a),) * 2, s0, actions)[1]
    return jax.device_get(jax.jit(run)(key))


def _expected(x: np.ndarray, stage_before: int = 0):
    """The contract's subtask rewards of the Slider task along positions x [T] (stage 0: [0, 1), stage 1: [1, 2])."""
    stages, rewards, success = [], [], []
    stage = stage_before
    for xi in x:
        stage = max(stage, int(xi >= 1.0))
        won = stage == 1 and xi >= 1.9
        r = [1.0, 1.0] if won else ([xi, 0.0] if stage == 0 else [1.0, float(np.clip(xi - 1.0, 0, 1))])
        stages.append(stage), rewards.append(r), success.append(won)
    return np.array(stages), np.array(rewards, np.float32), np.array(success)


def test_wrapper_rewards_follow_the_definition_on_a_script():
    env = make()
    # forward into stage 1, back across x = 1 (the stage must stay 1), then forward to success
    script = np.array([1] * 5 + [-1] * 3 + [1] * 6, np.float32)[:, None]
    s0, traj = _rollout(env, script)
    x0 = float(s0.pipeline_state)
    x = np.clip(x0 + 0.25 * np.cumsum(script[:, 0]), 0, 2)
    stages, rewards, success = _expected(x)
    end = int(np.argmax(success))  # the wrapper's episode ends at the first success; check up to there
    assert success.any() and stages[4] == 1 and x[7] < 1.0 and stages[7] == 1
    np.testing.assert_array_equal(traj.info["stage"][: end + 1], stages[: end + 1])
    np.testing.assert_allclose(traj.info["rewards"][: end + 1], rewards[: end + 1], atol=1e-6)
    np.testing.assert_allclose(traj.reward[: end + 1], rewards[: end + 1].sum(-1), atol=1e-6)
    np.testing.assert_array_equal(traj.metrics["success"][: end + 1], success[: end + 1].astype(np.float32))
    np.testing.assert_array_equal(traj.done[:end], 0.0)
    assert traj.done[end] == 1.0 and traj.info["truncation"][end] == 0.0
    np.testing.assert_array_equal(traj.info["steps"][: end + 1], np.arange(1, end + 2))
    # reset: stage 0, R = [x0, 0]; the obs ends with the stage one-hot
    np.testing.assert_allclose(s0.info["rewards"], [x0, 0.0], atol=1e-6)
    np.testing.assert_array_equal(s0.obs, np.array([x0, 1.0, 0.0], np.float32))
    np.testing.assert_array_equal(traj.obs[4, 1:], [0.0, 1.0])
    assert env.observation_size == 3 and env.action_size == 1 and env.num_stages == 2


def test_wrapper_stage_function_form_matches_tuple_form():
    spec = StageSpec(num_stages=2,
                     progress=lambda s, n: s.obs[0] - n.astype(jnp.float32),
                     completed=lambda s, n: s.obs[0] >= jnp.where(n == 0, 1.0, 1.9))
    script = np.array([1] * 4 + [-1] * 2 + [1] * 5, np.float32)[:, None]
    a = _rollout(StageWrapper(Slider(), spec, episode_length=50), script)[1]
    b = _rollout(make(), script)[1]
    for leaf in ("reward", "done"):
        np.testing.assert_array_equal(getattr(a, leaf), getattr(b, leaf))
    np.testing.assert_array_equal(a.info["stage"], b.info["stage"])
    np.testing.assert_array_equal(a.info["rewards"], b.info["rewards"])


def test_wrapper_time_limit_is_truncation_and_inner_done_is_termination():
    s0, traj = _rollout(StageWrapper(Slider(), SPEC, episode_length=3), np.zeros((3, 1), np.float32))
    np.testing.assert_array_equal(traj.done, [0, 0, 1])
    np.testing.assert_array_equal(traj.info["truncation"], [0, 0, 1])

    class Wall(Slider):  # the inner env ends the episode itself when x hits 0
        def step(self, state, action):
            s = super().step(state, action)
            return s.replace(done=(s.pipeline_state <= 0.0).astype(jnp.float32))

    class Timed(Slider):  # ... or says that its end was its own time limit
        def reset(self, rng):
            return super().reset(rng).replace(info={"truncation": jnp.float32(0)})

        def step(self, state, action):
            s = super().step(state, action)
            return s.replace(done=jnp.float32(1), info={"truncation": jnp.float32(1)})

    _, traj = _rollout(StageWrapper(Wall(), SPEC, episode_length=50), -np.ones((2, 1), np.float32))
    np.testing.assert_array_equal(traj.done, [1, 1])
    np.testing.assert_array_equal(traj.info["truncation"], [0, 0])
    np.testing.assert_array_equal(traj.metrics["success"], [0, 0])
    _, traj = _rollout(StageWrapper(Timed(), SPEC, episode_length=50), np.zeros((1, 1), np.float32))
    assert traj.done[0] == 1 and traj.info["truncation"][0] == 1


def test_wrapper_stage_never_decreases_jit_vmap_256():
    env = make()
    steps, batch = 40, 256

    @jax.jit
    def run(key):
        k0, k1 = jax.random.split(key)
        s0 = jax.vmap(env.reset)(jax.random.split(k0, batch))
        acts = jax.random.uniform(k1, (steps, batch, 1), minval=-1.0, maxval=1.0)
        return jax.lax.scan(lambda s, a: (jax.vmap(env.step)(s, a),) * 2, s0, acts)[1]

    traj = jax.device_get(run(jax.random.PRNGKey(1)))
    stage, done = traj.info["stage"], traj.done
    live = np.cumsum(done, axis=0) - done == 0  # steps up to and including each env's first done
    assert (np.diff(stage, axis=0)[live[1:]] >= 0).all()
    assert (stage == 1).any() and (stage == 0).any()  # both stages visited, so the check has teeth
    r = traj.info["rewards"]
    assert ((r >= 0) & (r <= 1)).all()
    np.testing.assert_allclose(traj.reward, r.sum(-1), atol=1e-6)
    assert violations(env, num_envs=batch, steps=20) == []


def test_stage_spec_is_validated():
    with pytest.raises(ValueError, match="num_stages"):
        StageSpec(num_stages=0, progress=(), completed=())
    with pytest.raises(ValueError, match="progress has 1 functions"):
        StageSpec(num_stages=2, progress=(lambda s: 0.0,), completed=lambda s, n: False)


# ---------------------------------------------------------------- a user's env through the training API


def test_train_cli_with_user_env(tmp_path):
    from ccp_jax import train

    out = tmp_path / "run"
    summary = train.main(["--env", "user_env_module:make", "--preset", "tiny", "--out", str(out), "--no-progress"])
    written = json.loads((out / "summary.json").read_text())
    assert written == json.loads(json.dumps(summary))
    config = json.loads((out / "config.json").read_text())
    assert config["task"]["env"] == "user_env_module:make" and config["num_stages"] == 2
    assert (out / "metrics.jsonl").read_text().strip()


@pytest.mark.parametrize("env, message", [
    ("user_env_module:make_broken", "env: user_env_module:make_broken is refused: env breaks the envs_mjx contract"),
    ("user_env_module:missing", "env: module 'user_env_module' has no factory 'missing'"),
    ("no_such_module_here:make", "env: cannot import 'no_such_module_here'"),
    ("user_env_module:make_raising",
     "env: the factory 'user_env_module:make_raising' raised RuntimeError: no licence for the simulator"),
    ("user_env_module:not_a_factory", "env: 'user_env_module:not_a_factory': user_env_module.not_a_factory is a "
                                      "int, not a factory"),
    ("user_env_module:make_late_nan", "env: user_env_module:make_late_nan is refused: env breaks the envs_mjx "
                                      "contract:\n  - obs not finite (step 70"),
])
def test_train_cli_refuses_bad_user_env_before_writing(tmp_path, env, message):
    from ccp_jax import ConfigError, train

    out = tmp_path / "run"
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        train.main(["--env", env, "--preset", "tiny", "--out", str(out), "--no-progress"])
    assert err.value.field == "env"
    assert not out.exists()


# ---------------------------------------------------------------- pusher


@pytest.fixture(scope="module")
def pusher():
    from envs_mjx.pusher import Pusher

    return Pusher(episode_length=150)


def test_pusher_meets_contract(pusher):
    assert (pusher.num_stages, pusher.observation_size, pusher.action_size) == (2, 25, 7)
    check_env(pusher, num_envs=4, steps=10)


@pytest.mark.slow  # 45 s cold on a quiet 2-core CPU, ~100 s under load: compiling the IK and the MJX step
def test_pusher_scripted_controller_succeeds(pusher):
    from envs_mjx.pusher import scripted_controller

    plan, act = scripted_controller(pusher)
    steps = 130

    def episode(key):
        s0 = pusher.reset(key)

        def body(carry, _):
            s, p = carry
            a, p = act(s, p)
            nxt = pusher.step(s, a)
            nxt = jax.tree.map(lambda old, new: jnp.where(s.done > 0, old, new), s, nxt)  # freeze when over
            return (nxt, p), (nxt.info["stage"], nxt.metrics["success"], nxt.info["rewards"])
        return jax.lax.scan(body, (s0, plan(s0)), None, length=steps)[1]

    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    stage, success, rewards = jax.device_get(jax.jit(jax.vmap(episode))(keys))
    won = success.max(axis=1) > 0
    assert won.sum() >= 3, f"successes {won}"
    for i in np.flatnonzero(won):
        t = int(np.argmax(success[i] > 0))
        assert stage[i, 0] == 0 and (stage[i, :t] == 1).any()  # reached the puck (stage 1), then pushed it
        assert stage[i, t] == 1 and (np.diff(stage[i]) >= 0).all()
        np.testing.assert_array_equal(rewards[i, t], [1.0, 1.0])


# ---------------------------------------------------------------- importing the envs is quiet


def test_import_drops_only_mujoco_warp_notices():
    """After envs_mjx.configure_cpu(), MJX's 'Failed to import warp' notices are dropped from stdout; other output of
    that import is kept."""
    import subprocess
    import sys

    script = ("import builtins, envs_mjx\nenvs_mjx.configure_cpu()\n"  # the CLI's call installs the filter
              "_print = builtins.print\n"  # each print of the import below gets a 'kept:' twin the filter must pass
              "builtins.print = lambda *a, **k: (_print(*a, **k), _print('kept:', *a, **k))\n"
              "import brax.envs.base\n"
              "builtins.print = _print\n"
              "import mujoco.mjx.warp as w; print('warp installed:', w.WARP_INSTALLED)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert not [line for line in lines if line.startswith("Failed to import")], lines
    if "warp installed: False" in lines:  # the notices were printed, and each one's twin passed the filter
        assert "kept: Failed to import warp: No module named 'warp'" in lines, lines
