"""Peg-in-hole control steps per second, arm and hand on MJX and C physics, side by side in one process.

For each model x physics (``--envs``) and batch size: ``jax.jit(jax.vmap(rollout))``, where ``rollout``
resets and then runs ``lax.scan`` over ``--steps`` control steps (10 physics steps each) with uniformly
random actions in [-1, 1]. Compile is excluded (one warm-up call). The timed calls alternate between the
envs, one call of each per trial, so all see the same load on a shared CPU; the figure is the median over
``--trials`` of batch * steps / seconds per call, and each env's ratio to the MJX arm is the median of the
trials' paired ratios.

    python experiments/bench/peg_speed.py                  # all four, batches 1 and 16
    python experiments/bench/peg_speed.py --envs arm-mjx hand-c --batches 1 16 64 --trials 7 --json out.json

Compiling takes ≈ 1-2 min per MJX env and batch on a 2-core CPU, seconds for C.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from envs_mjx import configure_cpu  # noqa: E402

ENVS = ("arm-mjx", "hand-mjx", "arm-c", "hand-c")  # model-physics
BASE = "arm-mjx"


def compiled_rollout(env, batch: int, steps: int):
    """A jitted fn(keys uint32[batch, 2]) -> final obs, running `steps` random-action control steps per env."""
    import jax

    def rollout(key):
        k_reset, k_act = jax.random.split(key)
        state = env.reset(k_reset)

        def body(s, k):
            a = jax.random.uniform(k, (env.action_size,), minval=-1.0, maxval=1.0)
            return env.step(s, a), None

        return jax.lax.scan(body, state, jax.random.split(k_act, steps))[0].obs

    return jax.jit(jax.vmap(rollout))


def measure(batch: int, steps: int, trials: int, envs: dict) -> dict:
    """Steps/s of every model at one batch size, the models' calls interleaved trial by trial."""
    import jax

    fns, compile_s = {}, {}
    for name, env in envs.items():
        fns[name] = compiled_rollout(env, batch, steps)
        t0 = time.perf_counter()
        jax.block_until_ready(fns[name](jax.random.split(jax.random.PRNGKey(0), batch)))
        compile_s[name] = time.perf_counter() - t0
    times = {name: [] for name in envs}
    for trial in range(trials):
        keys = jax.random.split(jax.random.PRNGKey(1 + trial), batch)
        for name, fn in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(keys))
            times[name].append(time.perf_counter() - t0)
    rates = {name: batch * steps / statistics.median(t) for name, t in times.items()}
    base = times.get(BASE)
    paired = {name: statistics.median(b / x for b, x in zip(base, t)) for name, t in times.items()} if base else {}
    return {"batch": batch, "steps": steps, "trials": trials, "steps_per_s": rates, "over_arm_mjx": paired,
            "compile_and_first_s": compile_s, "times_s": times}


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=list(ENVS), choices=ENVS, help="model-physics pairs")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    p.add_argument("--steps", type=int, default=100, help="control steps per env and call")
    p.add_argument("--trials", type=int, default=5)
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = p.parse_args(argv)

    import jax

    from envs_mjx.peg_in_hole import PegInHole

    info = {"jax": jax.__version__, "backend": jax.default_backend(), "cpu_count": os.cpu_count(),
            "machine": platform.machine(), "processor": platform.processor(),
            "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(json.dumps(info), flush=True)
    envs = {name: PegInHole(model=name.split("-")[0], physics=name.split("-")[1]) for name in args.envs}
    results = []
    for batch in args.batches:
        r = measure(batch, args.steps, args.trials, envs)
        results.append(r)
        print(f"batch {batch:3d} (median of {args.trials} interleaved calls of {args.steps} steps):", flush=True)
        for name in envs:
            ratio = f"{r['over_arm_mjx'][name]:5.1f}x the MJX arm" if r["over_arm_mjx"] else ""
            print(f"  {name:9s} {r['steps_per_s'][name]:8.1f} control steps/s  {ratio}  "
                  f"(compile+first {r['compile_and_first_s'][name]:.0f} s)", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"info": info, "results": results}, indent=1))
    return results


if __name__ == "__main__":
    configure_cpu()  # before JAX starts: MJX's XLA flag, as the CLI sets it
    main()
