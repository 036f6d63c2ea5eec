"""What C MuJoCo behind a JAX callback would give the peg env: control steps/s of the bare physics.

Not an env (that is `PegInHole(physics="c")`, timed by peg_speed.py): the measurement behind it, for
docs/peg.md#where-a-control-step-goes. The models' own physics (10 `mj_step`
of 2 ms per control step, C MuJoCo, one thread) is called from a jitted, vmapped `lax.scan` through
`jax.pure_callback` (vmap_method="broadcast_all": one host call per control step for the whole batch,
a Python loop over the batch inside), with random commands for the robot's actuators and the gripper.
Beside it, in the same process, the MJX arm env (`PegInHole(model="arm")`) at the same batch, timed
the same way as experiments/bench/peg_speed.py. What it leaves out: the env's controller, observation,
rewards and grasp check (< 5 % of an MJX control step, experiments/bench/peg_breakdown.py).

    python experiments/bench/peg_c_callback.py [--batches 1 16] [--steps 100] [--trials 5]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from envs_mjx import configure_cpu  # noqa: E402


def c_physics(asset: Path, n_substeps: int = 10):
    """(step_fn(qpos, qvel, warm, ctrl) -> same, for JAX, batched or not; nq, nv, nu) of one MuJoCo model."""
    import jax
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(asset))
    datas: list = []

    def host(qpos, qvel, warm, ctrl):
        shape = qpos.shape[:-1]
        qpos, qvel, warm, ctrl = (np.asarray(a, np.float64).reshape(-1, a.shape[-1]) for a in (qpos, qvel, warm, ctrl))
        while len(datas) < len(qpos):
            datas.append(mujoco.MjData(m))
        out = [np.empty_like(qpos), np.empty_like(qvel), np.empty_like(warm)]
        for i in range(len(qpos)):
            d = datas[i]
            d.qpos[:], d.qvel[:], d.qacc_warmstart[:], d.ctrl[:] = qpos[i], qvel[i], warm[i], ctrl[i]
            mujoco.mj_step(m, d, nstep=n_substeps)
            out[0][i], out[1][i], out[2][i] = d.qpos, d.qvel, d.qacc_warmstart
        return tuple(o.reshape(*shape, o.shape[-1]).astype(np.float32) for o in out)

    def step(qpos, qvel, warm, ctrl):
        shapes = tuple(jax.ShapeDtypeStruct(a.shape, np.float32) for a in (qpos, qvel, warm))
        return jax.pure_callback(host, shapes, qpos, qvel, warm, ctrl, vmap_method="broadcast_all")

    return step, m.nq, m.nv, m.nu, np.asarray(m.qpos0, np.float32)


def timed(fn, batch: int, trials: int) -> list[float]:
    import jax

    jax.block_until_ready(fn(jax.random.split(jax.random.PRNGKey(0), batch)))
    out = []
    for t in range(trials):
        keys = jax.random.split(jax.random.PRNGKey(1 + t), batch)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(keys))
        out.append(time.perf_counter() - t0)
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--trials", type=int, default=5)
    args = p.parse_args(argv)

    import jax
    import jax.numpy as jnp

    from envs_mjx.peg_in_hole import ASSET, HAND_ASSET, PegInHole

    arm_env = PegInHole(model="arm")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from peg_speed import compiled_rollout

    for batch in args.batches:
        fns = {"MJX arm env": compiled_rollout(arm_env, batch, args.steps)}
        for name, asset in (("C arm physics", ASSET), ("C hand physics", HAND_ASSET)):
            step, nq, nv, nu, qpos0 = c_physics(asset)

            def rollout(key, step=step, nv=nv, nu=nu, qpos0=qpos0):
                def body(s, k):
                    ctrl = jax.random.uniform(k, (nu,), minval=-0.1, maxval=0.1)
                    return step(*s, ctrl), None

                s0 = (jnp.asarray(qpos0), jnp.zeros(nv), jnp.zeros(nv))
                return jax.lax.scan(body, s0, jax.random.split(key, args.steps))[0][0]

            fns[name] = jax.jit(jax.vmap(rollout))
        rates = {name: batch * args.steps / statistics.median(timed(fn, batch, args.trials))
                 for name, fn in fns.items()}
        base = rates["MJX arm env"]
        print(f"batch {batch:3d}: " + ", ".join(f"{k} {v:8.1f} control steps/s ({v / base:.1f}x)"
                                                for k, v in rates.items()), flush=True)


if __name__ == "__main__":
    configure_cpu()  # before JAX starts
    main()
