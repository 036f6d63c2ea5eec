"""Joint-update throughput against the matmul roof, measured in one process.

    python experiments/bench/update_speed.py --hidden 256 256 --rooms 3 --grid 1

Prints: FLOPs of one joint update of all agents (XLA's own count), updates per
second (median of --reps timed scans of --loops updates, compile excluded),
the throughput of a bare jitted matmul chain with the layer's shapes, and the
fraction of that roof the update reaches; also the fraction of the 256-wide
chain's roof, the unit the prototype's speed is stated in (76 % at [256, 256], 53 % at [64, 64];
docs/design.md#the-learning-yardstick), so the two compare on machines of any speed.
"""
from __future__ import annotations

import dataclasses
import functools
import statistics
import time

import jax
import jax.numpy as jnp
import tyro

from ccp_jax import buffer as replay
from ccp_jax.buffer import ReplayBuffer
from ccp_jax.config import make_config
from ccp_jax.learner import init_agents, make_learner, make_networks, train_loops
from timed import SameWork, emitters_on_everywhere  # this folder: the script's own
from envs_mjx import configure_cpu


@dataclasses.dataclass
class Args:
    hidden: tuple[int, ...] = (256, 256)
    rooms: int = 3
    algo: str = "csac"
    grid: int = 1
    batch: int = 256
    loops: int = 50
    buffer: int = 10_000
    """Transitions per agent, all filled."""
    reps: int = 3
    obs: int = 24
    act: int = 2


def timed(f, *args, reps: int) -> float:
    jax.block_until_ready(f(*args))  # compile
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def matmul_roof(batch: int, width: int, reps: int) -> float:
    """FLOP/s of a jitted chain of [batch, width] @ [width, width] products."""
    x = jnp.ones((batch, width)) / width
    w = jnp.eye(width) + 1e-3
    chain = 200

    @jax.jit
    def f(x, w):
        return jax.lax.fori_loop(0, chain, lambda i, y: jnp.tanh(y @ w), x)

    return 2 * batch * width * width * chain / timed(f, x, w, reps=reps)


def add_roof(result: dict, work: SameWork) -> dict:
    """`result` with "roof_gflops", `matmul_roof` at `work`'s batch and widest layer, measured and printed
    (when `work.roof`): the context a SAC comparison reports beside its timings."""
    if work.roof:
        batch, width = work.batch, max(work.hidden)
        result["roof_gflops"] = matmul_roof(batch, width, reps=3) / 1e9
        print(f"jnp.dot roof at [{batch}, {width}] @ [{width}, {width}]: {result['roof_gflops']:.0f} GFLOP/s")
    return result


def full_of_noise(buffer: ReplayBuffer, key: jax.Array) -> ReplayBuffer:
    """`buffer` (any leading axes) with every slot filled with uniform [0, 1) values, cast to each leaf's dtype."""
    leaves, treedef = jax.tree.flatten(buffer.data)
    full = [jax.random.uniform(k, x.shape).astype(x.dtype) for k, x in zip(jax.random.split(key, len(leaves)), leaves)]
    return buffer.replace(data=jax.tree.unflatten(treedef, full), size=jnp.full_like(buffer.size, buffer.capacity))


def main(args: Args) -> dict:
    config = make_config("paper", rooms=args.rooms, algo=args.algo, hidden=args.hidden, batch_size=args.batch)
    n = config.num_agents
    nets = make_networks(config, args.act)
    learner = make_learner(config, nets, args.act)
    keys = jax.random.split(jax.random.PRNGKey(0), args.grid)
    agents = jax.vmap(lambda k: init_agents(nets, k, n, args.obs, args.act))(keys)
    r = config.num_agents if args.algo != "sac" else 1
    # Full buffers of random transitions: the trainer's loops then draw batches as late in training.
    empty = jax.vmap(lambda _: replay.init_buffer(replay.zero_transition(args.obs, args.act, r), n, args.buffer))(keys)
    buffer = full_of_noise(empty, keys[0])
    eta, ready = jnp.full((args.grid, n), 0.5), jnp.ones((args.grid, n), bool)

    @functools.partial(jax.jit, static_argnums=1)
    def many(agents, loops):  # the trainer's loops, every run of the grid
        run = lambda a, b, e, r, k: train_loops(learner, a, b, e, r, k, loops, args.batch)[0]
        return jax.vmap(run)(agents, buffer, eta, ready, jax.random.split(keys[0], args.grid))

    flops = many.lower(agents, 1).compile().cost_analysis()
    flops = (flops[0] if isinstance(flops, list) else flops)["flops"]

    per_update = timed(many, agents, args.loops, reps=args.reps) / args.loops
    roof = matmul_roof(args.batch, max(args.hidden), args.reps)
    roof_256 = roof if max(args.hidden) == 256 else matmul_roof(args.batch, 256, args.reps)
    result = {"hidden": args.hidden, "agents": n, "grid": args.grid, "gflop_per_joint_update": flops / 1e9,
              "joint_updates_per_s": 1 / per_update, "ms_per_agent_update": 1e3 * per_update / (n * args.grid),
              "achieved_gflops": flops / per_update / 1e9, "roof_gflops": roof / 1e9,
              "fraction_of_roof": flops / per_update / roof, "roof_256_gflops": roof_256 / 1e9,
              "fraction_of_roof_256": flops / per_update / roof_256}
    for k, v in result.items():
        print(f"{k:>24}: {v:.4g}" if isinstance(v, float) else f"{k:>24}: {v}")
    return result


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    emitters_on_everywhere()  # the update compiled as the trainer compiles the maze epoch
    main(tyro.cli(Args))
