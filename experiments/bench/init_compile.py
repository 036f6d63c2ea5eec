"""Compile time of the trainer's init at XLA's default LLVM optimisation against the O1 the trainer uses on a CPU.

    python experiments/bench/init_compile.py                        # 2-room maze and peg, one run each
    python experiments/bench/init_compile.py --envs maze --seeds 6  # a grid of 6

The init (agents' networks and optimisers, replay buffers, the envs' first states, vmapped over the grid)
runs once, but its program, mostly vmapped random initialisers, took as long to compile as a whole epoch.
`GridTrainer` compiles it with `devices.CPU_INIT_OPTIONS` (LLVM O1; for the maze also the fusion emitters
of its epoch). Both versions are traced, then compiled once each in this one process, O1 first (so one-time
costs of a process's first compile count against it), with no persistent compilation cache (a second compile
of the same program would hit JAX's in-memory cache); the table gives each one's XLA compile time (tracing
apart), their ratio, and whether the two states are equal bit for bit.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import tyro

from ccp_jax.config import make_config
from ccp_jax.envs import make_env
from ccp_jax.grid import make_grid_train
from ccp_jax.trainer import make_train
from envs_mjx import configure_cpu


@dataclasses.dataclass
class Args:
    envs: Sequence[str] = ("maze", "peg")
    """"maze" (2 rooms) and/or "peg", at the yardstick's "small" settings (docs/design.md#the-learning-yardstick)."""
    seeds: int = 1
    """Grid size."""


def compile_s(lowered) -> tuple[float, object]:
    start = time.perf_counter()
    compiled = lowered.compile()
    return time.perf_counter() - start, compiled


def main(args: Args) -> None:
    jax.config.update("jax_enable_compilation_cache", False)
    rows = []
    for name in args.envs:
        config = make_config("small", env=name, seeds=tuple(range(args.seeds)), buffer_size=200_000,
                             **({"rooms": 2} if name == "maze" else {}))
        env = make_env(config)
        grid = make_grid_train(config, env, devices=jax.devices()[:1])
        versions = {"default": jax.jit(jax.vmap(make_train(config, env).init)), "O1": grid._init}
        seeds = jnp.arange(args.seeds)
        lowered = {key: jitted.lower(seeds) for key, jitted in versions.items()}  # tracing kept out of the times
        times, states = {}, {}
        for key in ("O1", "default"):
            times[key], compiled = compile_s(lowered[key])
            states[key] = jax.device_get(compiled(seeds))
        same = all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(states["default"]),
                                                         jax.tree.leaves(states["O1"])))
        default, o1 = times["default"], times["O1"]
        rows.append((name, default, o1, default / o1, same))
    print(f"\ninit compile (s), grid of {args.seeds}, {jax.devices()[0].platform}")
    print(f"{'env':>5} {'default':>8} {'O1':>7} {'ratio':>6}  same bits")
    for name, default, o1, ratio, same in rows:
        print(f"{name:>5} {default:8.1f} {o1:7.1f} {ratio:6.2f}  {'yes' if same else 'no'}")


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main(tyro.cli(Args, description=__doc__))
