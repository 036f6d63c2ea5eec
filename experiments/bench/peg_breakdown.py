"""Where a peg-in-hole control step's time goes, per robot model (arm, hand), on one environment.

Each piece of MJX's physics step (`mujoco.mjx._src.forward.step`: kinematics, mass matrix, collision,
constraint rows, velocity terms, actuation, solver, integration) and the env's own per-control-step work
(the controller: the arm's IK and Jacobian; the observation, rewards and grasp check) is jitted on its own
and timed on a state in the middle of a thick-section grasp's insertion (pads, table and hole contacts
active), `--reps` applications inside one compiled loop, the best of `--trials` calls (the models' programs
take turns within each trial: the CPU may be shared). A control step is
`n_substeps` = 10 physics steps plus one controller and one observation; the script prints each piece
per control step (physics pieces x 10), its share, and the measured whole control step.

    python experiments/bench/peg_breakdown.py [--models arm hand] [--reps 20] [--trials 7]

Compiling takes ≈ 2-4 min per model on a 2-core CPU.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from envs_mjx import configure_cpu  # noqa: E402


def pieces(env):
    """(name, d -> d) for every piece of one physics step, in MJX's order, then the env's per-step work."""
    from mujoco.mjx._src import collision_driver, constraint, forward, smooth, solver

    m = env.sys

    def chain(*fns):
        def run(d):
            for fn in fns:
                d = fn(m, d)
            return d
        return run

    def controller(d):
        return d.replace(ctrl=env._control(env.readout(d), jax.numpy.array([1.0, 1.0])))

    def observe(d):
        ro = env.readout(d)  # the pad contacts and the Jacobian are read here
        obs = env._obs(ro)
        touch = ro.touch
        # fold the outputs into the state so that nothing is dead code
        return d.replace(time=d.time + obs.sum() * 0.0 + touch[0] * 0.0)

    return [
        ("kinematics (bodies, sites, com)", chain(smooth.kinematics, smooth.com_pos)),
        ("mass matrix (crb, factor)", chain(smooth.tendon, smooth.crb, smooth.tendon_armature, smooth.factor_m)),
        ("collision (13 pairs)", chain(collision_driver.collision)),
        ("constraint rows", chain(constraint.make_constraint, smooth.transmission)),
        ("velocity terms (com_vel, passive, rne)", chain(forward.fwd_velocity)),
        ("actuation + smooth acceleration", chain(forward.fwd_actuation, forward.fwd_acceleration)),
        ("solver (Newton)", chain(solver.solve)),
        ("integration (implicitfast)", chain(forward.implicit)),
        ("= one physics step (mjx.step)", chain(forward.step)),
        ("controller (arm: IK + Jacobian)", controller),
        ("observation + rewards + grasp check", observe),
    ]


def mid_insertion_state(env, steps: int):
    """The MJX data after `steps` control steps of the thick-section scripted grasp (policy 0)."""
    from envs_mjx.peg_in_hole import scripted_action

    def run(key):
        s = env.reset(key)

        def body(s, k):
            return env.step(s, scripted_action(s, jax.numpy.int32(0), k)), None

        return jax.lax.scan(body, s, jax.random.split(key, steps))[0]

    s = jax.jit(run)(jax.random.PRNGKey(3))
    return s.pipeline_state, s


def programs(model: str, reps: int, steps: int) -> list[tuple[str, Any, Any, int]]:
    """(piece name, compiled program, its argument, applications per call) for every piece of one model."""
    from envs_mjx.peg_in_hole import PegInHole

    env = PegInHole(model=model)
    d, state = mid_insertion_state(env, steps)
    print(f"{model}: nq {env.mj_model.nq}, nv {env.mj_model.nv}, stage {int(state.info['stage'])}, "
          f"depth {float(env.peg_depth(d)):.3f} m, contacts {int((d._impl.contact.dist < 0).sum())} "
          f"of {d._impl.contact.dist.shape[0]}, constraint rows {d._impl.efc_J.shape[0]}", flush=True)
    out = []
    for name, fn in pieces(env):
        out.append((name, jax.jit(lambda d, fn=fn: jax.lax.fori_loop(0, reps, lambda _, x: fn(x), d)), d, reps))
    action = jax.numpy.array([1.0, 1.0])
    step = jax.jit(lambda s: jax.lax.fori_loop(0, 10, lambda _, x: env.step(x, action), s))
    out.append(("= one control step (env.step)", step, state, 10))
    for _, fn, arg, _ in out:  # compile
        jax.block_until_ready(fn(arg))
    return out


def breakdown(models: list[str], reps: int, trials: int, steps: int) -> dict[str, dict[str, float]]:
    """Seconds per application of every piece, per model: the best of `trials` calls, the models' programs
    timed in turn within each trial so that both see the same load on a shared CPU."""
    progs = {m: programs(m, reps, steps) for m in models}
    best: dict[str, dict[str, float]] = {m: {} for m in models}
    for _ in range(trials):
        for m, entries in progs.items():
            for name, fn, arg, n in entries:
                t0 = time.perf_counter()
                jax.block_until_ready(fn(arg))
                t = (time.perf_counter() - t0) / n
                best[m][name] = min(best[m].get(name, t), t)
    return best


def report(model: str, t: dict[str, float], n_substeps: int) -> None:
    per_control = {k: v * (n_substeps if i < 9 else 1) for i, (k, v) in enumerate(t.items())}
    whole = per_control["= one control step (env.step)"]
    print(f"\n{model}: per control step ({n_substeps} physics steps), one env", flush=True)
    for k, v in per_control.items():
        print(f"  {k:40s} {v * 1e3:8.3f} ms  {100 * v / whole:5.1f} %", flush=True)
    pieces_sum = sum(v for k, v in per_control.items() if not k.startswith("="))
    print(f"  {'sum of the pieces':40s} {pieces_sum * 1e3:8.3f} ms  {100 * pieces_sum / whole:5.1f} %", flush=True)
    print(f"  control steps/s: {1 / whole:.0f}", flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["arm", "hand"], choices=["arm", "hand"])
    p.add_argument("--reps", type=int, default=20, help="applications per compiled call")
    p.add_argument("--trials", type=int, default=7)
    p.add_argument("--steps", type=int, default=90, help="control steps of the scripted grasp before timing")
    args = p.parse_args(argv)
    print(f"jax {jax.__version__}, {jax.default_backend()}, {os.cpu_count()} CPUs, "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}", flush=True)
    results = breakdown(args.models, args.reps, args.trials, args.steps)
    for m, t in results.items():
        report(m, t, 10)
    if len(results) == 2:
        a, h = results["arm"], results["hand"]
        print("\narm / hand per piece: " + ", ".join(f"{k.split(' (')[0].lstrip('= ')} {a[k] / h[k]:.1f}x"
                                                     for k in a), flush=True)


if __name__ == "__main__":
    configure_cpu()  # before JAX starts
    import jax  # noqa: E402  (after configure_cpu: the XLA flags are read when JAX starts)
    import jax.numpy  # noqa: E402,F401

    main()
