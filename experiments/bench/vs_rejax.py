"""Our trainer (one agent, algo="sac") against rejax's SAC, same maze, same work, one process.

    pip install -e ".[bench]"                             # rejax 0.1.3 (with the gymnax 0.0.9 it was written for)
    python experiments/bench/vs_rejax.py                  # [64, 64], the paper's epoch; one run, then a grid of 4 seeds
    python experiments/bench/vs_rejax.py --hidden 256 256 --grids 1

rejax trains gymnax environments; the maze reaches it through rejax's own
adapter for brax environments (`rejax.compat.brax2gymnax.Brax2GymnaxEnv`), as
a rejax user would bring one. Both sides get the settings of vs_brax.py
(`timed.SameWork`): actor and twin critic [w, w] ReLU, batch 256, Adam 3e-4,
γ 0.95, τ 0.005 (rejax's polyak 0.995, every step), 5 envs, one update per
step of the 5 envs (the paper's 5000 env steps and 1000 updates per epoch),
buffer 1e5, the first 1000 env steps without updates.

rejax's `train` runs `eval_freq / num_envs` iterations (a step of every env,
then `num_epochs` updates) and then evaluates; with `eval_freq` = the epoch's
env steps and `skip_initial_evaluation`, one call of its jitted `train` on the
carried state is one epoch. Its evaluation is rejax's `evaluate` on
`eval_episodes` episodes of ≤ `episode_length` steps (sampled actions, its only
mode); ours evaluates as in training (deterministic, docs/design.md#hyperparameters). Each side is
timed twice: with its evaluation, and with evaluation stubbed out (the same
work on both sides).

A grid of G seeds is trained the way each library offers: rejax's `train`
`jax.vmap`ped over G states (its README's recipe), ours the grid trainer with G
seeds (`--members-at-once` by default: on this 2-core CPU as one device, 4
[64, 64] SAC members vmapped; also timed one at a time).

What differs beyond the arithmetic, as each library does it: gymnax's `step`
computes a fresh reset at every step and selects it where an episode ended
(ours resets only when one did); rejax treats the maze's time limit as a
termination (ours bootstraps through it); rejax updates actor, critics and
temperature one after another, each with its own forward pass (ours one joint
gradient).

Timing, compile excluded: each epoch is one call timed to
`block_until_ready`. The calls that compile are dropped: ours compiles once;
rejax's state starts with weak-typed leaves (log α and its Adam moments) that
turn strong one per call, and each new set of leaf types compiles its `train`
again (3 compiles; their sum, less 3 warm epochs, is its compile time).
Rounds run one epoch of each program in turn, so each round's ratio compares
epochs under the same machine load; the ratio reported is the median over
rounds of rejax epoch s / our epoch s.
"""
from __future__ import annotations

import dataclasses
import statistics
import sys
from pathlib import Path
from unittest import mock

import jax
import jax.numpy as jnp
import tyro

from envs_mjx.maze import Maze

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timed import SameWork, TimedEpochs, avals, emitters_on_everywhere, our_sac, updates_per_epoch  # noqa: E402
from update_speed import add_roof  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class Args(SameWork):
    grids: tuple[int, ...] = (1, 4)
    """Grid sizes G (seeds trained together in one program)."""
    rounds: int = 5
    """Timed epochs of each program; one of each per round."""
    uniform_probe: bool = True
    """Also time rejax with its sampler replaced by ours (uniform, with replacement), evaluation stubbed."""
    ours_one_at_a_time: bool = True
    """For G > 1, also time ours with the members one at a time (`--members-at-once 1`), evaluation stubbed."""


def uniform_sample(buffer, num: int, rng: jax.Array):
    """A stand-in for rejax's `ReplayBuffer.sample`: `num` indices uniform over the filled slots, with replacement.

    rejax draws without replacement (`jax.random.choice(..., replace=False, p=...)` over the whole capacity),
    whose cost grows with the buffer; ours and brax's draw with replacement (`replay.sample_indices`).
    """
    idx = jax.random.randint(rng, (num,), 0, buffer.num_entries)
    return jax.tree.map(lambda arr: arr[idx], buffer.data)


class RejaxRun(TimedEpochs):
    """rejax's SAC on the maze, G seeds vmapped, compiled and warmed; `epoch()` runs and times one `train` call."""

    def __init__(self, args: SameWork, seeds: tuple[int, ...], evaluate: bool, uniform: bool = False):
        from rejax import SAC
        from rejax.buffers import ReplayBuffer
        from rejax.compat.brax2gymnax import Brax2GymnaxEnv
        from rejax.evaluate import evaluate as rejax_evaluate

        env = Brax2GymnaxEnv(Maze(rooms=args.rooms, episode_length=args.episode_length))
        params = env.default_params
        algo = SAC.create(
            env=env, env_params=params, num_envs=args.num_envs, num_epochs=args.grad_updates_per_step,
            buffer_size=args.buffer, fill_buffer=args.start_steps, batch_size=args.batch, learning_rate=3e-4,
            gamma=0.95, polyak=1 - 0.005, hidden_layer_sizes=args.hidden, total_timesteps=args.epoch_steps,
            eval_freq=args.epoch_steps, skip_initial_evaluation=True)

        def eval_callback(algo, ts, rng):
            if not evaluate:
                return jnp.zeros(())
            _, returns = rejax_evaluate(algo.make_act(ts), rng, env, params, args.eval_episodes,
                                              args.episode_length)
            return returns.mean()

        algo = algo.replace(eval_callback=eval_callback)
        self._train = jax.jit(jax.vmap(lambda ts: algo.train(train_state=ts)), donate_argnums=0)
        keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
        # The targets start as the critics' own arrays: copies, so the state can be donated.
        self.state = jax.tree.map(jnp.copy, jax.block_until_ready(jax.vmap(algo.init_state)(keys)))
        self.times: list[float] = []
        sampler = uniform_sample if uniform else ReplayBuffer.sample
        seen: list[list[tuple]] = []
        with mock.patch.object(ReplayBuffer, "sample", sampler):  # read whenever `train` is traced
            # rejax's state starts with weak-typed leaves (log α, its Adam moments) that turn strong one per
            # call, and each call on a state of new leaf types compiles `train` again: 3 compiles here.
            while avals(self.state) not in seen:
                seen.append(avals(self.state))
                self.epoch()
            warm = self.epoch()
        self.compiles = len(seen)
        self.compile_s = sum(self.times[:-1]) - self.compiles * warm  # the first epoch also fills the prefill
        self.times.clear()

    def _step(self):
        self.state, evaluation = self._train(self.state)
        return self.state, evaluation


# Each program: its label, and the rejax program doing the same work (the ratio's numerator).
PROGRAMS = {
    "rejax_no_eval": ("rejax SAC", "rejax_no_eval"),
    "rejax": ("rejax SAC, with its evaluation", "rejax"),
    "rejax_uniform": ("rejax SAC, our sampler", "rejax_no_eval"),
    "ours_no_eval": ("ours", "rejax_no_eval"),
    "ours": ("ours, with its evaluation", "rejax"),
    "ours_one": ("ours, members one at a time", "rejax_no_eval"),
}


def paired(num: list[float], den: list[float]) -> list[float]:
    return [a / b for a, b in zip(num, den)]


def report(rows: list[dict], args: Args) -> str:
    """A markdown table: per grid size, each program's epoch time and its ratios to rejax's, paired by round.

    rows: {"grid": G, "programs": {name: {"times": [s per round], "compile_s": s}}}.
    """
    lines = ["| G | program | s per epoch | rejax / this, same work (min–max) | rejax with our sampler / this "
             "| compile s |", "|---|---|---|---|---|---|"]
    for row in rows:
        progs = row["programs"]
        for name, (label, rejax) in PROGRAMS.items():
            if name not in progs:
                continue
            times = progs[name]["times"]
            ratios = paired(progs[rejax]["times"], times)
            vs_uniform = (f"{statistics.median(paired(progs['rejax_uniform']['times'], times)):.2f}"
                          if "rejax_uniform" in progs and rejax == "rejax_no_eval" else "")
            lines.append(f"| {row['grid']} | {label} | {statistics.median(times):.2f} | "
                         f"{statistics.median(ratios):.2f} ({min(ratios):.2f}–{max(ratios):.2f}) | {vs_uniform} | "
                         f"{progs[name]['compile_s']:.1f} |")
    lines.append(f"\nPer epoch: {args.epoch_steps} env steps and {updates_per_epoch(args)} updates per seed; epoch s "
                 "covers all G seeds. Ratios: medians over rounds of the paired ratio; > 1: this program is faster. "
                 "Without 'with its evaluation', evaluation is stubbed. 'Our sampler': rejax with its replay sampler "
                 "replaced by uniform draws with replacement (`uniform_sample`).")
    return "\n".join(lines)


def main(args: Args) -> dict:
    print(f"maze rooms={args.rooms}, hidden={args.hidden}, batch={args.batch}, num_envs={args.num_envs}, "
          f"{args.epoch_steps} env steps + {updates_per_epoch(args)} updates per epoch, grids {args.grids}, "
          f"{args.rounds} rounds; devices={jax.devices()}", flush=True)
    rows = []
    for grid in args.grids:
        seeds = tuple(range(grid))
        runs = {"rejax": RejaxRun(args, seeds, evaluate=True), "rejax_no_eval": RejaxRun(args, seeds, evaluate=False),
                "ours": our_sac(args, seeds, evaluate=True), "ours_no_eval": our_sac(args, seeds, evaluate=False)}
        if args.uniform_probe:
            runs["rejax_uniform"] = RejaxRun(args, seeds, evaluate=False, uniform=True)
        if grid > 1 and args.ours_one_at_a_time:
            runs["ours_one"] = our_sac(args, seeds, evaluate=False, members_at_once=1)
        for r in range(args.rounds):
            line = ", ".join(f"{name} {run.epoch():.2f}" for name, run in runs.items())
            print(f"  G={grid} round {r}: {line} s", flush=True)
        rows.append({"grid": grid, "programs": {name: {"times": run.times, "compile_s": run.compile_s}
                                                for name, run in runs.items()}})
        del runs
    text = report(rows, args)
    print("\n" + text)
    return add_roof({"args": dataclasses.asdict(args), "rows": rows}, args)


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    emitters_on_everywhere()  # both sides compile alike (timed.py)
    main(tyro.cli(Args))
