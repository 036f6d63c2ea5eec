"""The peg env on C MuJoCo (``PegInHole(physics="c")``, envs_mjx/peg_c.py): exact state, determinism,
batching, sharding, the contract, and agreement with MJX.

tests/test_peg.py runs every scripted check on both physics; here, per model, one compiled program rolls
out 8 environments (jit + vmap + lax.scan, ~5 s to compile and run on a 2-core CPU) and the tests read it.
The comparison with MJX compiles an MJX rollout per model (~50 s hand, ~80 s arm).
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

from envs_mjx import cpu_xla_flags

os.environ["XLA_FLAGS"] = cpu_xla_flags()  # the MJX comparison; harmless for C

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from envs_mjx import peg_in_hole as P  # noqa: E402
from envs_mjx.peg_c import STATE_SPEC  # noqa: E402
from envs_mjx.peg_in_hole import PegInHole, scripted_action  # noqa: E402

B, T = 8, 60  # environments, control steps: through the approach and the grasp
POLICIES = jnp.array([0, 0, 1, 1, 2, 2, 3, 3], jnp.int32)  # thick, centre, grasp-release, random


def _one(env: PegInHole, steps: int = T):
    """fn(key, policy) -> (reset state, states [steps]): one env's whole State at every step."""

    def one(key, policy):
        k_reset, k_act = jax.random.split(key)
        s0 = env.reset(k_reset)

        def body(s, k):
            s2 = env.step(s, scripted_action(s, policy, k))
            return s2, s2

        return s0, jax.lax.scan(body, s0, jax.random.split(k_act, steps))[1]

    return one


def _rollout(env: PegInHole, steps: int = T):
    """jit(vmap(`_one`)) over keys [B] and policies [B]."""
    return jax.jit(jax.vmap(_one(env, steps)))


@pytest.fixture(scope="module", params=P.MODELS)
def env(request):
    return PegInHole(episode_length=T, model=request.param, physics="c")


@pytest.fixture(scope="module")
def run(env):
    keys = jax.random.split(jax.random.PRNGKey(3), B)
    fn = _rollout(env)
    s0, traj = fn(keys, POLICIES)
    return {"fn": fn, "keys": keys, "s0": jax.device_get(s0), "traj": jax.device_get(traj)}


def _equal(a, b) -> None:
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_same_key_same_bits(run):
    s0, traj = run["fn"](run["keys"], POLICIES)
    _equal((s0, traj), (run["s0"], run["traj"]))
    assert np.asarray(run["traj"].pipeline_state.state).dtype == np.uint32


def test_carried_state_is_c_mujocos_own_trajectory(env, run):
    """The uint32 words are mjSTATE_INTEGRATION's float64s: set into a fresh MjData and stepped with the
    recorded commands, C MuJoCo reproduces every next state bit for bit (nothing else of MjData matters)."""
    m = env.mj_model
    bits = np.concatenate([run["s0"].pipeline_state.state[:, None], run["traj"].pipeline_state.state], axis=1)
    states = bits.view(np.float64)  # [B, T + 1, S]
    ctrls = run["traj"].pipeline_state.ctrl
    d = mujoco.MjData(m)
    nxt = np.empty(states.shape[-1])
    for i in (0, 2, 7):
        for t in range(T):
            mujoco.mj_setState(m, d, states[i, t], STATE_SPEC)
            d.ctrl[:] = ctrls[i, t]
            mujoco.mj_step(m, d, nstep=env.n_substeps)
            mujoco.mj_getState(m, d, nxt, STATE_SPEC)
            np.testing.assert_array_equal(nxt.view(np.uint32), bits[i, t + 1], err_msg=(i, t))
    # The readout's qpos and qvel are the state's, rounded to float32.
    np.testing.assert_array_equal(run["traj"].pipeline_state.qpos, env.exact_qpos(run["traj"].pipeline_state)
                                  .astype(np.float32))


def test_nested_vmap_split_batches_and_one_env_agree(env, run):
    """One host call serves any batch layout: members x envs (vmap of vmap), halves, or one env alone."""
    one = jax.jit(lambda k, p: jax.tree.map(lambda x: x[None], _one(env)(k, p)))
    grid = jax.jit(jax.vmap(jax.vmap(_one(env))))
    s0, traj = grid(run["keys"].reshape(2, 4, 2), POLICIES.reshape(2, 4))
    _equal(jax.tree.map(lambda x: x.reshape((B,) + x.shape[2:]), (s0, traj)), (run["s0"], run["traj"]))
    i = 5
    _equal(one(run["keys"][i], POLICIES[i]), jax.tree.map(lambda x: x[i:i + 1], (run["s0"], run["traj"])))


def test_resume_from_host_copy_is_bit_identical(env, run):
    """A state taken to the host mid-episode (as a checkpoint does) and brought back continues exactly."""
    det = np.flatnonzero(np.asarray(POLICIES) < 3)  # the scripted policies (the random one drew from the scan's keys)
    t = T // 2
    half = jax.tree.map(lambda x: jnp.asarray(np.array(x[det, t - 1])), run["traj"])
    act = jax.vmap(scripted_action, in_axes=(0, 0, None))(half, POLICIES[det], jax.random.PRNGKey(0))
    _equal(jax.jit(jax.vmap(env.step))(half, act), jax.tree.map(lambda x: x[det, t], run["traj"]))


def test_grasps_happen_and_stages_agree_with_the_readout(run):
    stage = run["traj"].info["stage"]
    assert (stage[np.asarray(POLICIES) < 3, -1] == 1).all()  # every scripted grasp was detected by step 60
    touch = run["traj"].pipeline_state.readout.touch
    assert touch.dtype == bool and touch[np.asarray(POLICIES) < 2, -1].all()  # thick / centre: still holding


def test_non_finite_physics_ends_the_episode_as_truncation(env, run):
    """C MuJoCo resets a diverged simulation and warns; the env reports it as MJX's NaN state would show."""
    s = jax.tree.map(lambda x: jnp.asarray(x[0]), run["s0"])
    bad = np.array(s.pipeline_state.state).view(np.float64)
    bad[1:1 + env.mj_model.nq] = np.nan
    s = s.replace(pipeline_state=s.pipeline_state.replace(state=jnp.asarray(bad.view(np.uint32))))
    s2 = jax.jit(env.step)(s, jnp.zeros(2))
    assert float(s2.done) == 1.0 and float(s2.info["truncation"]) == 1.0
    np.testing.assert_array_equal(np.asarray(s2.obs), 0.0)


def test_env_contract():
    from envs_mjx.contract import violations

    assert violations(PegInHole(episode_length=60, model="hand", physics="c"), num_envs=4) == []


def test_render_frames_reads_the_exact_state(env, run):
    from brax.envs.base import State

    states = jax.tree.map(lambda x: x[0, ::30], run["traj"])
    assert isinstance(states, State)
    np.testing.assert_allclose(env.exact_qpos(states.pipeline_state), states.pipeline_state.qpos, atol=1e-6)
    try:
        frames = env.render_frames(states)
    except RuntimeError as err:
        assert "MUJOCO_GL" in str(err)
        pytest.skip(f"no offscreen GL: {err}")
    assert frames.shape == (2, 240, 320, 3) and frames.dtype == np.uint8 and frames.std() > 5.0


# C against MJX, closed loop: the same resets and scripted policies, each physics under its own env.
AGREE_STEPS = 40  # the approach, up to where the first fingers close on the peg (grasps are detected at 38-56)
AGREE_TOL = 1.5e-3  # metres: measured at most 1.0 mm (grip point) and 0.4 mm (peg centre) on both models


def test_c_and_mjx_agree_over_the_first_steps(env, run):
    """From the same reset (the same qpos to float32 rounding: the reset draws in JAX), the same policies give
    the same grip point and peg centre within 1.5 mm over the first 40 steps; each grasp is detected within 3
    steps of the other physics' and every env ends in the same stage.

    The two differ by float32 against float64 and by their collision and solver code, and closed loop the
    controller feeds the differences back. Once the fingers squeeze the peg the contacts amplify them (6-10 mm
    apart at step 60, the grasp a step or two earlier or later), so from there on the physics are compared by
    outcome (tests/test_peg.py: the same scripted outcomes on both)."""
    mjx_env = PegInHole(episode_length=T, model=env.model, physics="mjx")
    s0, traj = _rollout(mjx_env)(run["keys"], POLICIES)
    np.testing.assert_allclose(np.asarray(s0.pipeline_state.qpos), run["s0"].pipeline_state.qpos, atol=1e-7)
    n = AGREE_STEPS
    for name in ("grip_pos", "peg_pos"):
        sl = P.OBS_SLICES[name]
        diff = np.abs(np.asarray(traj.obs)[:, :n, sl] - run["traj"].obs[:, :n, sl]).max()
        assert diff < AGREE_TOL, (name, diff)
    stage_m, stage_c = np.asarray(traj.info["stage"]), run["traj"].info["stage"]
    np.testing.assert_array_equal(stage_m[:, -1], stage_c[:, -1])
    grasped = stage_c[:, -1] == 1
    t_m, t_c = (stage_m >= 1).argmax(1)[grasped], (stage_c >= 1).argmax(1)[grasped]
    assert np.abs(t_m - t_c).max() <= 3, (t_m, t_c)


SHARDED = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    from envs_mjx.peg_in_hole import PegInHole, scripted_action
    assert jax.device_count() == 2
    env = PegInHole(episode_length=20, model="hand", physics="c")

    def one(key, policy):
        s = env.reset(key)
        def body(s, k):
            s2 = env.step(s, scripted_action(s, policy, k))
            return s2, s2.pipeline_state.state
        return jax.lax.scan(body, s, jax.random.split(key, 20))[1]

    keys, pol = jax.random.split(jax.random.PRNGKey(1), 4), jnp.array([0, 1, 2, 3], jnp.int32)
    ref = np.asarray(jax.jit(jax.vmap(one))(keys, pol))
    mesh = Mesh(np.array(jax.devices()), ("grid",))
    spec = PartitionSpec("grid")
    sm = jax.jit(jax.shard_map(jax.vmap(one), mesh=mesh, in_specs=(spec, spec), out_specs=spec, check_vma=False))
    sharded = jax.device_put((keys, pol), NamedSharding(mesh, spec))
    out = sm(*sharded)
    assert len(out.sharding.device_set) == 2
    np.testing.assert_array_equal(np.asarray(out), ref)
    auto = jax.jit(jax.vmap(one), out_shardings=NamedSharding(mesh, spec))(*sharded)
    np.testing.assert_array_equal(np.asarray(auto), ref)
    print("EQUAL")
""")


def test_sharded_over_two_cpu_devices_gives_the_one_device_bits():
    """shard_map (the grid's) and automatic sharding over 2 simulated CPU devices: each device's host call
    steps its own rows, with its own MjData pool, and the bits equal one device's."""
    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run([sys.executable, "-c", SHARDED], env=env, capture_output=True, text=True, timeout=600,
                         cwd=root)
    assert out.returncode == 0 and "EQUAL" in out.stdout, out.stderr[-3000:]
