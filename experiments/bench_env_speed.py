"""Environment speed: control steps per second for 1, 64 and 1024 parallel environments.

For each env and batch size: ``jax.jit(jax.vmap(rollout))`` where ``rollout`` resets
and then runs ``lax.scan`` over ``--steps`` control steps with uniformly random actions
in [-1, 1]. Compile is excluded (one warm-up call); the figure is the median of
``--reps`` timed repetitions (each as many back-to-back calls as fill 0.5 s, divided
out): batch * steps / seconds per call. Peg-in-hole control steps are
``n_substeps`` = 10 MJX physics steps each (so physics steps/s = 10x the figure).

    python experiments/bench_env_speed.py                 # peg and maze, 1 / 64 / 1024 envs
    python experiments/bench_env_speed.py --envs 1 64 --only peg --json out.json

On CPU the XLA flag --xla_cpu_use_fusion_emitters=false is appended to XLA_FLAGS
(unless the flag is already set) before JAX starts: the peg env is ~50x slower without it.
The maze (envs_mjx.maze.Maze) is skipped with a note if it cannot be imported.
"""
from __future__ import annotations

import os

from envs_mjx import cpu_xla_flags

os.environ["XLA_FLAGS"] = cpu_xla_flags()

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402

# Default scan lengths per batch size: long enough to time, short enough for a 2-core CPU.
DEFAULT_STEPS = {1: 200, 64: 40, 1024: 8}


def make_envs(only: str | None):
    envs = {}
    if only in (None, "peg"):
        from envs_mjx.peg_in_hole import PegInHole

        envs["peg"] = PegInHole()
    if only in (None, "maze"):
        try:
            from envs_mjx.maze import Maze
        except Exception as err:  # noqa: BLE001 - another module, maybe not written yet
            print(f"maze: skipped (cannot import envs_mjx.maze.Maze: {err!r})", flush=True)
        else:
            try:
                envs["maze"] = Maze()
            except TypeError:
                envs["maze"] = Maze(rooms=2)
    return envs


def bench(env, batch: int, steps: int, reps: int, seed: int = 0) -> dict:
    def rollout(key):
        k_reset, k_act = jax.random.split(key)
        state = env.reset(k_reset)

        def body(s, k):
            a = jax.random.uniform(k, (env.action_size,), minval=-1.0, maxval=1.0)
            return env.step(s, a), None

        state, _ = jax.lax.scan(body, state, jax.random.split(k_act, steps))
        return state.obs, state.reward

    fn = jax.jit(jax.vmap(rollout))
    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(keys))
    compile_s = time.perf_counter() - t0
    # Calls per timed repetition: enough for >= 0.5 s, so fast envs (the maze) time well.
    t0 = time.perf_counter()
    jax.block_until_ready(fn(keys))
    calls = max(1, math.ceil(0.5 / max(time.perf_counter() - t0, 1e-6)))
    times = []
    for r in range(reps):
        keys = jax.random.split(jax.random.PRNGKey(seed + 1 + r), batch)
        t0 = time.perf_counter()
        for _ in range(calls):
            out = fn(keys)
        jax.block_until_ready(out)
        times.append((time.perf_counter() - t0) / calls)
    med = statistics.median(times)
    return {"batch": batch, "steps": steps, "reps": reps, "calls_per_rep": calls,
            "compile_and_first_s": round(compile_s, 2),
            "times_s": [round(t, 5) for t in times], "median_s": round(med, 5),
            "env_steps_per_s": round(batch * steps / med, 1)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024], help="batch sizes")
    p.add_argument("--steps", type=int, default=None, help="scan length (default: per batch size)")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--only", choices=["peg", "maze"], default=None)
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = p.parse_args(argv)

    info = {"jax": jax.__version__, "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()],
            "cpu_count": os.cpu_count(), "machine": platform.machine(), "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(json.dumps(info), flush=True)
    results = []
    for name, env in make_envs(args.only).items():
        extra = f", {env.n_substeps} physics steps per control step" if hasattr(env, "n_substeps") else ""
        print(f"{name}: obs {env.observation_size}, actions {env.action_size}{extra}", flush=True)
        for b in args.envs:
            steps = args.steps or DEFAULT_STEPS.get(b, max(4, 4096 // b))
            r = {"env": name, **bench(env, b, steps, args.reps)}
            results.append(r)
            print(f"  {name:5s} envs={b:5d}  {r['env_steps_per_s']:>10.1f} env steps/s  "
                  f"(median of {args.reps}: {r['median_s']} s per call of {steps} steps; "
                  f"compile+first {r['compile_and_first_s']} s)",
                  flush=True)
    if args.json:
        args.json.write_text(json.dumps({"info": info, "results": results}, indent=1))
    return results


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main()
