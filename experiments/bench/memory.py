"""Device memory of a training grid: bytes per stored transition, the paper's Table I grid, what fits a GPU.

    python experiments/bench/memory.py                   # Table I: 9 ratios × 5 seeds, 4-room maze (4 agents), 1e6/agent
    python experiments/bench/memory.py --ratios 3 --seeds 5 --rooms 3 --gpus 24 40 80

1. Layout. The bytes of one transition are read off the real replay buffer
   (`jax.eval_shape` of the trainer's `init`, so nothing is allocated) and
   checked against the formula 4 · (2·obs + act + 2 + 2R) for float32 fields
   obs, next_obs [obs], action [act], terminal [], rewards and completed [R]
   (R = N reward channels for CSAC/Naive, 1 for SAC), and the int32 next_stage [].
2. The grid. G runs × N agents × capacity × bytes, plus the rest of each run's
   state (parameters, target critics, Adam moments, env states), also read off
   `eval_shape`.
3. Ways to fit it, each marked exact (trains the same as the paper's
   per-agent 1e6 FIFO buffers) or not, against each GPU size with only
   `usable` of its memory available to arrays (JAX preallocates 75 % of a GPU
   by default: set XLA_PYTHON_CLIENT_MEM_FRACTION=.95 for a grid this large).
4. Checks. `--xla`: XLA's own buffer assignment for the compiled, donated
   `train_step` of the full-size grid (lowered from shapes only, never
   allocated; on this machine's backend) gives argument, output, alias and
   temporary bytes: whether the epoch needs memory beyond the state (e.g. a
   copy of the buffers); its temporaries are added to every layout in 3.
   `--verify`: a real small grid is allocated and the sum of `nbytes` over
   its leaves is compared with the formula.
"""
from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
import tyro

from ccp_jax.config import make_config
from ccp_jax.envs import make_env
from ccp_jax.trainer import make_train
from envs_mjx import configure_cpu

GB = 1e9


@dataclasses.dataclass
class Args:
    rooms: int = 4
    algo: str = "csac"
    ratios: int = 9
    seeds: int = 5
    buffer: int = 1_000_000
    """Capacity per agent (the paper's 1e6)."""
    total_steps: int = 3_000_000
    """Env steps per run: bounds the data all agents of a run receive together."""
    hidden: tuple[int, ...] = (256, 256)
    batch: int = 256
    gpus: tuple[float, ...] = (40.0, 80.0)
    """GPU memory sizes in GB (1e9 bytes)."""
    usable: float = 0.9
    """Fraction of a GPU's memory assumed available to arrays (CUDA context, allocator slack)."""
    verify: bool = True
    """Allocate a small grid and compare its nbytes with the formula."""
    xla: bool = True
    """Compile the full-size grid's train_step from shapes and print XLA's memory analysis."""


def config_for(args: Args, grid: int | None = None, buffer: int | None = None):
    etas = tuple((round(0.1 * (i + 1), 3),) for i in range(args.ratios)) if args.algo == "csac" else ((0.1,),)
    seeds = tuple(range(args.seeds if grid is None else grid))
    if grid is not None:
        etas = etas[:1]
    return make_config("paper", rooms=args.rooms, algo=args.algo, etas=etas, seeds=seeds, hidden=args.hidden,
                       batch_size=args.batch, buffer_size=buffer or args.buffer, total_steps=args.total_steps)


def nbytes(tree) -> int:
    return sum(math.prod(x.shape) * np.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree))


def run_shapes(config):
    """Shapes of one run's TrainState (no allocation)."""
    trainer = make_train(config, make_env(config))
    return jax.eval_shape(trainer.init, jnp.int32(0))


def transition_fields(state) -> dict[str, int]:
    """Bytes per transition of each buffer field (leaves are [N, capacity, ...])."""
    data = state.buffer.data
    return {name: math.prod(x.shape[2:]) * np.dtype(x.dtype).itemsize for name, x in zip(data._fields, data)}


def gib(x: float) -> str:
    return f"{x / GB:.1f}"


def main(args: Args) -> dict:
    config = config_for(args)
    env = make_env(config)
    n, g, cap = config.num_agents, config.grid_size, config.sac.buffer_size
    obs, act = env.observation_size, env.action_size
    r = 1 if n == 1 else config.num_stages
    state = run_shapes(config)

    # 1. Layout.
    fields = transition_fields(state)
    per_transition = sum(fields.values())
    formula = 4 * (2 * obs + act + 2 + 2 * r)
    print(f"Transition layout ({config.task.env}, {config.num_stages} stages, {config.algo}: N = {n} agents, R = {r} "
          f"reward channels, obs {obs}, act {act}):")
    for name, b in fields.items():
        print(f"  {name:<10}{b:>5} B")
    print(f"  {'total':<10}{per_transition:>5} B   formula 4·(2·{obs} + {act} + 2 + 2·{r}) = {formula} B "
          f"[{'agrees' if formula == per_transition else 'DIFFERS'}]")

    # 2. The grid.
    buffers_run = nbytes(state.buffer)
    other_run = nbytes(state) - buffers_run
    total = g * (buffers_run + other_run)
    print(f"\nGrid: {g} runs ({args.ratios if args.algo == 'csac' else 1} ratios × {args.seeds} seeds) × {n} agents "
          f"× {cap:,} transitions × {per_transition} B")
    print(f"  buffers {gib(g * buffers_run)} GB + rest of the state {gib(g * other_run)} GB "
          f"({other_run / 1e6:.1f} MB per run: parameters, targets, Adam moments, env states) = {gib(total)} GB")

    result: dict = {}
    temp_per_run = 0.0
    if args.xla:
        trainer = make_train(config, env)
        step = jax.jit(jax.vmap(trainer.train_step), donate_argnums=0)
        shapes = jax.eval_shape(jax.vmap(trainer.init), jax.ShapeDtypeStruct((g,), jnp.int32))
        eta = jax.ShapeDtypeStruct((g, n), jnp.float32)
        t = time.perf_counter()
        m = step.lower(shapes, eta).compile().memory_analysis()
        sec = time.perf_counter() - t
        if m is None:
            print("\nXLA memory analysis: not available on this backend")
        else:
            fields = ("argument_size_in_bytes", "output_size_in_bytes", "alias_size_in_bytes", "temp_size_in_bytes")
            vals = {f: getattr(m, f) for f in fields}
            peak = vals["argument_size_in_bytes"] + vals["output_size_in_bytes"] - vals["alias_size_in_bytes"] + \
                vals["temp_size_in_bytes"]
            print(f"\nXLA buffer assignment of the donated train_step for the full grid on {jax.devices()[0].platform} "
                  f"(compiled from shapes in {sec:.0f} s, nothing allocated):")
            for f, v in vals.items():
                print(f"  {f:<24}{gib(v):>8} GB")
            print(f"  {'peak = args + out − alias + temp':<24}{gib(peak):>8} GB (formula: {gib(total)} GB of state)")
            result["xla"] = {**vals, "peak": peak}
            temp_per_run = vals["temp_size_in_bytes"] / g

    # 3. Ways to fit it. Every env step goes to exactly one agent's buffer, so a run's agents hold at most
    # min(N · capacity, total_steps) transitions between them.
    pooled = min(n * cap, args.total_steps)
    # Slim per-agent rows: agent n reads only reward/completed channels n and n + 1; flags and next_stage fit in uint8.
    ch = min(r, 2)
    slim = 4 * (2 * obs + act) + 4 * ch + 1 + ch + 1
    # Pooled trajectory storage: obs once per step (next_obs = the following row, plus the final obs of each
    # episode), all R channels once, uint8 flags and stage, and an int32 index per agent's sample list.
    dedup = 4 * (obs + act + r) + 1 + r + 1 + 4
    rest = g * (other_run + temp_per_run)  # per program: the rest of the state and XLA's temporaries
    options = [
        ("as now, buffer_size 1e6 (paper)", "yes", "none", g * n * cap * per_transition + rest),
        ("split the grid in 2 programs (max of 2)", "yes", "none; run 2 invocations",
         math.ceil(g / 2) * (n * cap * per_transition + other_run + temp_per_run)),
        ("split the grid in 3 programs (max of 3)", "yes", "none; run 3 invocations",
         math.ceil(g / 3) * (n * cap * per_transition + other_run + temp_per_run)),
        (f"buffer_size {args.total_steps // n:,} (= steps / N)", "no*", "none",
         g * n * (args.total_steps // n) * per_transition + rest),
        ("slim rows: uint8 flags, 2 reward channels", "yes", "buffer.py, collect, learner",
         g * n * cap * slim + rest),
        (f"pooled per run ({pooled:,} slots), slim rows", "yes", "buffer.py (shared pool, per-agent FIFO)",
         g * pooled * (slim + 4) + rest),
        ("pooled trajectory rows, obs stored once", "yes", "buffer.py (SB3-style)", g * pooled * dedup + rest),
        ("as now with obs in bfloat16", "no", "buffer.py", g * n * cap * (per_transition - 4 * obs) + rest),
    ]
    head = f"{'layout':<44}{'exact':>6}{'GB':>7}" + "".join(f"{f'{s:g} GB':>8}" for s in args.gpus)
    print(f"\nWhat fits (GB = buffers + rest of the state + XLA temporaries "
          f"({'from the analysis above' if temp_per_run else 'not measured: --xla'}), per program; "
          f"assuming {args.usable:.0%} of a GPU usable by arrays):")
    print(head + "   code change")
    for name, exact, change, b in options:
        fits = "".join(f"{'fits' if b <= args.usable * s * GB else '—':>8}" for s in args.gpus)
        print(f"{name:<44}{exact:>6}{gib(b):>7}{fits}   {change}")
    print(f"  * exact only while no agent receives more than {args.total_steps // n:,} transitions in a run "
          f"(its buffer would overwrite data the paper's would keep); config.sac.buffer_size is one capacity for all "
          f"agents, and the first agent usually receives the most.")

    result.update({"bytes_per_transition": per_transition, "formula": formula, "grid_bytes": total,
              "buffers_bytes": g * buffers_run, "other_bytes": g * other_run,
              "options": [dict(layout=o[0], exact=o[1], change=o[2], bytes=o[3]) for o in options]})

    # 4. Checks.
    if args.verify:
        small = config_for(args, grid=2, buffer=1000)
        trainer = make_train(small, make_env(small))
        real = jax.block_until_ready(jax.jit(jax.vmap(trainer.init))(jnp.arange(2)))
        measured = sum(x.nbytes for x in jax.tree.leaves(real.buffer))
        predicted = 2 * small.num_agents * 1000 * formula + 2 * 2 * small.num_agents * 4  # + ptr, size int32[N]
        print(f"\nCheck, allocated: grid 2 × {small.num_agents} agents × 1000 transitions: buffers "
              f"{measured:,} B measured (jax nbytes), {predicted:,} B predicted "
              f"[{'agrees' if measured == predicted else 'DIFFERS'}]; whole state {nbytes(real):,} B")
        result["verify"] = {"measured": measured, "predicted": predicted}
    return result


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main(tyro.cli(Args))
