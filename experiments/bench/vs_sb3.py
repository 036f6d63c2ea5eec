"""Our joint update against stable-baselines3's PyTorch SAC, per agent-update, one process.

    pip install -e ".[bench]"        # torch==2.13.0 (CPU build), stable-baselines3, gymnasium
    python experiments/bench/vs_sb3.py                         # widths 256 and 64, ours with 1 and 3 agents
    python experiments/bench/vs_sb3.py --widths 256 --agents 1 3 --grid 5

Same hyperparameters on both sides: MLPs [w, w] ReLU for the actor and each of
the twin critics, batch 256, Adam 3e-4 for actor, critics and temperature,
γ 0.95, τ 0.005, automatic entropy tuning with target −|A|. SB3 drives our maze
through `envs_mjx.gym.GymEnv`.

What is timed (compile excluded):
* SB3 updates: `model.train(gradient_steps=K, batch_size)` on a replay buffer
  filled with `fill` random maze transitions: replay sampling, critic, actor and
  temperature steps, target update.
* ours updates: a jitted `lax.scan` of K loops of exactly the trainer's loop
  body (`learner.train_loops`: batches from the agents' full ring buffers, the
  learner's joint update of all agents), for 1 agent (algo="sac") and for N agents
  (algo="csac", N rooms: each agent's update then also carries the
  cooperative cross-critic terms, i.e. more work than a SAC update), over a
  grid of `grid` runs. Per agent-update = time / (K · N · grid).
* end to end (`--e2e-steps`, 0 to skip): SB3 `learn()` with one env and one
  update every 5 env steps (the paper's ratio) against our `train_step`
  (one env, same ratio, evaluation stubbed out), one agent, env steps per second.
The two stacks alternate for `rounds` rounds (SB3, then ours right after), and
each ratio is the median over rounds of the paired ratio, so a change of load
on a shared machine hits both sides of a pair alike.
"""
from __future__ import annotations

import dataclasses
import functools
import statistics
import sys
import time
from pathlib import Path
from unittest import mock

import jax
import jax.numpy as jnp
import tyro

import ccp_jax.trainer as trainer_module
from ccp_jax import buffer as replay
from ccp_jax.config import make_config
from ccp_jax.learner import make_learner, make_networks, train_loops
from ccp_jax.grid import make_grid_train
from ccp_jax.trainer import make_train
from envs_mjx.maze import Maze

sys.path.insert(0, str(Path(__file__).resolve().parent))
from envs_mjx.gym import GymEnv  # noqa: E402
from update_speed import full_of_noise, matmul_roof  # noqa: E402
from timed import no_eval  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class Args:
    widths: tuple[int, ...] = (256, 64)
    """Hidden width w of the [w] * layers MLPs; every width is measured."""
    layers: int = 2
    agents: tuple[int, ...] = (1, 3)
    """Our agent counts: 1 = end-to-end SAC; N > 1 = CSAC on an N-room maze."""
    grid: int = 1
    """Our runs vmapped together (per agent-update figures divide by it)."""
    rooms: int = 2
    """Maze rooms for the single-agent runs (SB3 and ours)."""
    batch: int = 256
    loops: int = 50
    """Updates per timed call (ours: one scan; SB3: one model.train call)."""
    reps: int = 3
    """Repetitions for the matmul roofs."""
    rounds: int = 5
    """Paired measurements: each round times SB3 once, then ours once per agent count."""
    torch_threads: tuple[int, ...] = (1, 2)
    """SB3 is timed at each torch.set_num_threads value; ratios are against the fastest (SB3's best).
    On an oversubscribed machine torch's 2-thread OpenMP kernels can be many times slower than 1 thread;
    a thread count more than 3x slower than the best in round 0 is not timed again."""
    buffer: int = 100_000
    fill: int = 5000
    """Random transitions in SB3's buffer before its updates are timed (ours are filled with random data)."""
    e2e_steps: int = 2000
    """Env steps per end-to-end epoch (0 skips the end-to-end comparison)."""
    roof: bool = True
    """Also measure the jnp.dot and torch.mm roofs at [batch, w] @ [w, w]."""


# ----------------------------------------------------------------------------- SB3
def make_sb3(args: Args, width: int, train_freq: int = 1):
    import torch
    from stable_baselines3 import SAC

    torch.manual_seed(0)
    model = SAC("MlpPolicy", GymEnv(Maze(rooms=args.rooms)), learning_rate=3e-4, buffer_size=args.buffer,
                learning_starts=args.fill, batch_size=args.batch, tau=0.005, gamma=0.95, train_freq=train_freq,
                gradient_steps=1, ent_coef="auto", target_entropy="auto",
                policy_kwargs=dict(net_arch=[width] * args.layers), device="cpu", seed=0, verbose=0)
    model.learn(total_timesteps=args.fill)  # uniform-random actions until learning_starts: fills, no updates
    return model


def sb3_updates(args: Args, width: int):
    """A callable that runs `loops` SB3 gradient updates (sampling included) and returns seconds per update."""
    model = make_sb3(args, width)
    model.train(gradient_steps=5, batch_size=args.batch)  # warm-up

    def run() -> float:
        t = time.perf_counter()
        model.train(gradient_steps=args.loops, batch_size=args.batch)
        return (time.perf_counter() - t) / args.loops
    return run


def sb3_e2e(args: Args, width: int):
    """A callable that runs SB3 `learn()` for e2e_steps env steps (1 update / 5 steps); returns env steps/s."""
    model = make_sb3(args, width, train_freq=5)
    model.learn(total_timesteps=100, reset_num_timesteps=False)  # warm-up

    def run() -> float:
        t = time.perf_counter()
        model.learn(total_timesteps=args.e2e_steps, reset_num_timesteps=False)
        return args.e2e_steps / (time.perf_counter() - t)
    return run


# ----------------------------------------------------------------------------- ours
def our_config(args: Args, width: int, n_agents: int, **overrides):
    algo, rooms = ("sac", args.rooms) if n_agents == 1 else ("csac", n_agents)
    return make_config("paper", algo=algo, rooms=rooms, hidden=(width,) * args.layers, batch_size=args.batch,
                       buffer_size=args.buffer, **overrides)


def our_updates(args: Args, width: int, n_agents: int):
    """(callable running `loops` joint updates of the grid, returning seconds per joint update;
    XLA's FLOPs of one joint update of the grid)."""
    config = our_config(args, width, n_agents)
    env = Maze(rooms=config.task.rooms)
    trainer = make_train(config, env)
    nets = make_networks(config, env.action_size)
    learner = make_learner(config, nets, env.action_size)
    n = config.num_agents

    state = jax.jit(jax.vmap(trainer.init))(jnp.arange(args.grid))
    key = jax.random.PRNGKey(1)
    buffer = full_of_noise(state.buffer, key)
    eta = jnp.full((args.grid, n), 0.5)
    ready = replay.ready(buffer, config.sac.batch_size)

    @functools.partial(jax.jit, static_argnums=5)
    def many(agents, buffer, eta, ready, key, loops=args.loops):  # the trainer's loops, every run of the grid
        run = lambda a, b, e, r, k: train_loops(learner, a, b, e, r, k, loops, config.sac.batch_size)[0]
        return jax.vmap(run)(agents, buffer, eta, ready, jax.random.split(key, args.grid))

    cost = many.lower(state.agents, buffer, eta, ready, key, 1).compile().cost_analysis()
    flops = (cost[0] if isinstance(cost, list) else cost)["flops"]
    jax.block_until_ready(many(state.agents, buffer, eta, ready, key))  # compile

    def run() -> float:
        t = time.perf_counter()
        jax.block_until_ready(many(state.agents, buffer, eta, ready, key))
        return (time.perf_counter() - t) / args.loops
    return run, flops


def our_e2e(args: Args, width: int):
    """A callable that runs one epoch of e2e_steps env steps (1 env, 1 update / 5 steps, no eval); env steps/s."""
    config = our_config(args, width, 1, num_envs=1, steps_per_epoch=args.e2e_steps,
                        train_loops_per_epoch=args.e2e_steps // 5, total_steps=1000 * args.e2e_steps, start_steps=0)
    with mock.patch.object(trainer_module, "make_evaluate", no_eval):
        trainer = make_grid_train(config, Maze(rooms=config.task.rooms))
    eta, seeds = (jnp.asarray(x) for x in config.grid_arrays())
    box = [trainer.init(seeds)]

    def run() -> float:
        t = time.perf_counter()
        box[0], metrics = trainer.train_step(box[0], eta)
        jax.block_until_ready((box[0], metrics))
        return args.e2e_steps / (time.perf_counter() - t)
    run()  # compile
    return run


def torch_roof(batch: int, width: int, reps: int) -> float:
    import torch

    x, w = torch.ones(batch, width) / width, torch.eye(width) + 1e-3
    chain = 200

    def f():
        y = x
        for _ in range(chain):
            y = torch.tanh(y @ w)
        return y

    f()
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return 2 * batch * width * width * chain / statistics.median(times)


def main(args: Args) -> dict:
    import torch

    print(f"SB3 SAC (torch {torch.__version__}, threads {args.torch_threads}) vs ours (jax {jax.__version__}, "
          f"{jax.devices()}); batch {args.batch}, {args.layers} hidden layers, grid {args.grid}; "
          f"{args.rounds} rounds of [SB3 {args.loops} updates, then ours {args.loops} updates per agent count]")
    results = []
    for width in args.widths:
        sb3_run = sb3_updates(args, width)
        ours_runs = {n: our_updates(args, width, n) for n in args.agents}
        flops = {n: f for n, (_, f) in ours_runs.items()}
        sb3, ours, ratio = [], {n: [] for n in args.agents}, {n: [] for n in args.agents}
        by_threads = {t: [] for t in args.torch_threads}
        for r in range(args.rounds):
            for t in args.torch_threads:
                if r > 0 and by_threads[t][0] > 3 * min(x[0] for x in by_threads.values()):
                    by_threads[t].append(by_threads[t][-1])  # hopeless here (see round 0): not timed again
                    continue
                torch.set_num_threads(t)
                by_threads[t].append(sb3_run())
            sb3.append(min(x[-1] for x in by_threads.values()))  # SB3's best this round
            for n in args.agents:
                ours[n].append(ours_runs[n][0]() / (n * args.grid))  # seconds per agent-update
                ratio[n].append(sb3[-1] / ours[n][-1])
            print(f"  w={width} round {r}: SB3 " + ", ".join(f"{1e3 * x[-1]:.2f} ({t} thr)" for t, x in
                                                            by_threads.items()) + " ms/update; ours " + ", ".join(
                f"N={n} {1e3 * ours[n][-1]:.2f} ms/agent-update" for n in args.agents), flush=True)
        sb3_ms = 1e3 * statistics.median(sb3)
        row = {"width": width, "sb3_ms_per_update": sb3_ms, "ours": {},
               "sb3_ms_by_threads": {t: 1e3 * statistics.median(x) for t, x in by_threads.items()}}
        for n in args.agents:
            ms = 1e3 * statistics.median(ours[n])
            row["ours"][n] = {"ms_per_agent_update": ms, "ratio_vs_sb3": statistics.median(ratio[n]),
                              "ratio_min": min(ratio[n]), "ratio_max": max(ratio[n]),
                              "gflop_per_agent_update": flops[n] / (n * args.grid) / 1e9}
        if args.e2e_steps:
            best = min(row["sb3_ms_by_threads"], key=row["sb3_ms_by_threads"].get)
            torch.set_num_threads(best)
            sb3_e, ours_e = sb3_e2e(args, width), our_e2e(args, width)
            pairs = [(sb3_e(), ours_e()) for _ in range(args.rounds)]
            row["e2e"] = {"sb3_env_steps_per_s": statistics.median(p[0] for p in pairs),
                          "ours_env_steps_per_s": statistics.median(p[1] for p in pairs),
                          "ratio": statistics.median(o / s for s, o in pairs)}
            print(f"  w={width} end to end: SB3 " + ", ".join(f"{p[0]:.0f}" for p in pairs) + " env steps/s; ours "
                  + ", ".join(f"{p[1]:.0f}" for p in pairs), flush=True)
        if args.roof:
            row["roof_gflops"] = {"jnp.dot": matmul_roof(args.batch, width, args.reps) / 1e9,
                                  "torch.mm": torch_roof(args.batch, width, args.reps) / 1e9}
        results.append(row)

    print()
    print(f"{'width':>6}{'trainer':>30}{'ms/agent-upd':>14}{'agent-upd/s':>13}{'ours/SB3':>10}{'(min–max)':>13}"
          f"{'GFLOP/s':>9}")
    for row in results:
        sac_flop = row["ours"].get(1, {}).get("gflop_per_agent_update")
        sb3_gflops = f"{sac_flop / row['sb3_ms_per_update'] * 1e3:9.1f}" if sac_flop else f"{'':>9}"
        for t, ms in row["sb3_ms_by_threads"].items():
            print(f"{row['width']:>6}{f'SB3 SAC, torch {t} thread(s)':>30}{ms:>14.2f}{1e3 / ms:>13.0f}"
                  f"{row['sb3_ms_per_update'] / ms:>10.2f}")
        print(f"{row['width']:>6}{'SB3 SAC, best per round':>30}{row['sb3_ms_per_update']:>14.2f}"
              f"{1e3 / row['sb3_ms_per_update']:>13.0f}{1.0:>10.2f}{'':>13}{sb3_gflops}")
        for n, o in row["ours"].items():
            name = "ours SAC, 1 agent" if n == 1 else f"ours CSAC, {n} agents"
            spread = f"{o['ratio_min']:.2f}–{o['ratio_max']:.2f}"
            print(f"{'':>6}{name + (f' ×{args.grid} runs' if args.grid > 1 else ''):>30}"
                  f"{o['ms_per_agent_update']:>14.2f}{1e3 / o['ms_per_agent_update']:>13.0f}"
                  f"{o['ratio_vs_sb3']:>10.2f}{spread:>13}"
                  f"{o['gflop_per_agent_update'] / o['ms_per_agent_update'] * 1e3:>9.1f}")
        if "roof_gflops" in row:
            print(f"{'':>6}{'roofs [B,w]@[w,w]':>30}  jnp.dot {row['roof_gflops']['jnp.dot']:.1f} GFLOP/s, "
                  f"torch.mm {row['roof_gflops']['torch.mm']:.1f} GFLOP/s (at SB3's faster thread count)")
        if "e2e" in row:
            e = row["e2e"]
            print(f"{'':>6}{'end to end, 1 agent':>30}  SB3 {e['sb3_env_steps_per_s']:.0f} env steps/s, ours "
                  f"{e['ours_env_steps_per_s']:.0f} env steps/s: ours/SB3 {e['ratio']:.2f}x "
                  f"(one env, one update per 5 env steps, torch at SB3's faster thread count)")
    print("ours/SB3: median over rounds of the paired ratio (SB3 s per update / our s per agent-update).\n"
          "GFLOP/s: XLA's FLOP count of our update over the measured time (SB3 row: the 1-agent count, "
          "same networks and batch).")
    return {"args": dataclasses.asdict(args), "results": results}


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main(tyro.cli(Args))
