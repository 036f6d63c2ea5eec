"""Our trainer (one agent, algo="sac") against brax's SAC trainer, same maze, same work, one process.

    python experiments/bench/vs_brax.py                      # [256, 256], paper epoch, 2 rounds
    python experiments/bench/vs_brax.py --hidden 64 64 --epoch-steps 2000

Both train end-to-end SAC on `envs_mjx.maze.Maze(rooms)` with the same network
sizes (actor and twin critic), batch, number of envs, buffer capacity and
gradient updates per env step. brax interleaves one actor step of `num_envs`
envs with `grad_updates_per_step` updates; our epoch collects `epoch_steps`
env steps and then runs `epoch_steps · grad_updates_per_step / num_envs`
updates: the same work per epoch (the paper's 5000 steps / 1000 updates is
num_envs 5, one update per actor step).

Timing, compile excluded:
* brax: its own per-epoch `training/sps` (wall time of one pmapped
  `training_epoch`, which excludes evaluation), read through `progress_fn`.
  The first epoch of each brax training includes the compile; it is dropped,
  and compile is reported as (first epoch − median epoch).
* ours: each `train_step` call is timed to `block_until_ready`; the trainer
  is compiled (and warmed) before brax starts. Reported twice: the real
  `train_step` (which also evaluates `eval_episodes` deterministic episodes
  every epoch) and the same step with evaluation stubbed out, which is the
  work brax's timer covers.
* pairing: right after each brax epoch, inside brax's `progress_fn` and
  outside its timer, one epoch of each of ours runs. Each brax epoch and the
  ours that follows it share the machine's load at that moment; the reported
  ratio is the median over pairs of (brax epoch s / our epoch s). On a shared
  machine absolute numbers drift; the ratio is the result.

brax's wrappers keep their own float step counter and truncation and, on
auto-reset, restore only `pipeline_state` and `obs` (not `info`), so the maze
is given to brax through `BraxMaze`, which carries the whole maze state in
`pipeline_state` and leaves the time limit to brax's `EpisodeWrapper`.
"""
from __future__ import annotations

import dataclasses
import functools
import statistics
import sys
from pathlib import Path

import jax
import numpy as np
import tyro
from brax.envs.base import Env, State

from envs_mjx.maze import Maze

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timed import SameWork, emitters_on_everywhere, our_sac, updates_per_epoch  # noqa: E402
from update_speed import add_roof  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class Args(SameWork):
    hidden: tuple[int, ...] = (256, 256)
    """Hidden layers of actor and each critic (both trainers)."""
    epochs: int = 3
    """Timed epochs per brax training (plus its first epoch, which compiles)."""
    rounds: int = 2
    """brax trainings; after each brax epoch one epoch of each of ours runs, so the pairs share the load."""


class BraxMaze(Env):
    """The maze as brax's trainer sees it: obs, reward, done (success only) and metrics.

    The whole maze `State` rides in `pipeline_state`, so brax's auto-reset
    restores all of it (stage included); the inner time limit is disabled and
    brax's `EpisodeWrapper` truncates at `episode_length` instead.
    """

    def __init__(self, rooms: int):
        self.maze = Maze(rooms=rooms, episode_length=2**30)

    def _outer(self, inner: State) -> State:
        return State(pipeline_state=inner, obs=inner.obs, reward=inner.reward, done=inner.done,
                     metrics={"success": inner.metrics["success"]}, info={})

    def reset(self, rng: jax.Array) -> State:
        return self._outer(self.maze.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        inner = self.maze.step(state.pipeline_state, action)
        return state.replace(pipeline_state=inner, obs=inner.obs, reward=inner.reward, done=inner.done,
                             metrics={**state.metrics, "success": inner.metrics["success"]})

    @property
    def observation_size(self) -> int:
        return self.maze.observation_size

    @property
    def action_size(self) -> int:
        return self.maze.action_size

    @property
    def backend(self) -> str:
        return "jax"


def restore_device_put_replicated() -> None:
    """Puts back `jax.device_put_replicated` (removed in jax 0.10), which brax 0.14.2's trainers call.

    JAX's migration guide's replacement: the value stacked once per device, sharded over them.
    """
    try:
        jax.device_put_replicated  # noqa: B018 (deprecated but present before jax 0.10)
        return
    except AttributeError:
        pass

    def device_put_replicated(x, devices):
        sharding = jax.sharding.NamedSharding(jax.sharding.Mesh(np.array(devices), ("d",)),
                                              jax.sharding.PartitionSpec("d"))
        return jax.device_put(jax.tree.map(lambda a: np.stack([np.asarray(a)] * len(devices)), x), sharding)

    jax.device_put_replicated = device_put_replicated


def run_brax(args: Args, seed: int, after_epoch=lambda: None) -> dict:
    """One brax SAC training of (epochs + 1) epochs; per-epoch wall times from its own timer.

    `after_epoch()` runs right after each training epoch (inside brax's progress_fn, outside its timer).
    """
    from brax.training.agents.sac import networks as sac_networks
    from brax.training.agents.sac import train as sac

    restore_device_put_replicated()
    sps: list[float] = []

    def progress(step, metrics):
        if "training/sps" in metrics:
            sps.append(float(metrics["training/sps"]))
            after_epoch()

    epochs = args.epochs + 1
    sac.train(
        environment=BraxMaze(args.rooms),
        num_timesteps=args.start_steps + epochs * args.epoch_steps,
        episode_length=args.episode_length,
        num_envs=args.num_envs,
        num_eval_envs=args.eval_episodes,
        learning_rate=3e-4,
        discounting=0.95,
        seed=seed,
        batch_size=args.batch,
        num_evals=epochs + 1,  # an initial eval, then one after every epoch
        tau=0.005,
        min_replay_size=args.start_steps,
        max_replay_size=args.buffer,
        grad_updates_per_step=args.grad_updates_per_step,
        deterministic_eval=True,
        network_factory=functools.partial(sac_networks.make_sac_networks, hidden_layer_sizes=args.hidden),
        progress_fn=progress,
    )
    if len(sps) != epochs:
        raise RuntimeError(f"brax reported {len(sps)} training epochs, expected {epochs}")
    times = [args.epoch_steps / s for s in sps]
    return {"epoch_s": times, "compile_s": times[0] - statistics.median(times[1:])}


def main(args: Args) -> dict:
    updates = updates_per_epoch(args)
    print(f"maze rooms={args.rooms}, hidden={args.hidden}, batch={args.batch}, num_envs={args.num_envs}, "
          f"{args.epoch_steps} env steps + {updates} updates per epoch, {args.rounds} brax trainings × "
          f"{args.epochs} timed epochs, each followed by one epoch of each of ours; devices={jax.devices()}")
    ours = {"ours": our_sac(args, (0,), evaluate=True), "ours_no_eval": our_sac(args, (0,), evaluate=False)}
    runs = {"brax": [], "ours": [], "ours_no_eval": []}
    compiles = {"brax": [], **{k: [o.compile_s] for k, o in ours.items()}}
    for r in range(args.rounds):
        for o in ours.values():
            o.times.clear()
        out = run_brax(args, r, after_epoch=lambda: [o.epoch() for o in ours.values()])
        runs["brax"] += out["epoch_s"][1:]  # the first brax epoch compiles
        compiles["brax"].append(out["compile_s"])
        for k, o in ours.items():
            runs[k] += o.times[1:]  # paired with the timed brax epochs
        print(f"  round {r}: brax " + ", ".join(f"{x:.2f}" for x in out["epoch_s"][1:]) + " s; ours " +
              ", ".join(f"{x:.2f}" for x in ours["ours"].times[1:]) + " s; ours no eval " +
              ", ".join(f"{x:.2f}" for x in ours["ours_no_eval"].times[1:]) + " s", flush=True)

    rows = {}
    for name, times in runs.items():
        med = statistics.median(times)
        rows[name] = {"epoch_s": med, "env_steps_per_s": args.epoch_steps / med, "updates_per_s": updates / med,
                      "compile_s": statistics.median(compiles[name]), "spread": (max(times) - min(times)) / med}
    # Ratios of paired epochs (run back to back, so under the same machine load), then their median.
    paired = {k: statistics.median(b / o for b, o in zip(runs["brax"], runs[k])) for k in ("ours", "ours_no_eval")}
    print()
    print(f"{'trainer':<28}{'epoch s':>9}{'env steps/s':>13}{'updates/s':>11}{'ms/update*':>12}"
          f"{'compile s':>11}{'spread':>8}{'ours/brax':>11}")
    labels = {"brax": "brax SAC (training/sps)", "ours": "ours, train_step (+eval)", "ours_no_eval": "ours, no eval (= brax's)"}
    for name, row in rows.items():
        print(f"{labels[name]:<28}{row['epoch_s']:>9.2f}{row['env_steps_per_s']:>13.0f}{row['updates_per_s']:>11.1f}"
              f"{1e3 / row['updates_per_s']:>12.2f}{row['compile_s']:>11.1f}{row['spread']:>8.0%}"
              f"{paired.get(name, 1.0):>11.2f}")
    print(f"* epoch wall time / updates per epoch (env steps included). spread = (max − min) / median over "
          f"{len(runs['brax'])} epochs. ours/brax = median over epochs of brax epoch / the paired epoch of ours "
          f"(throughput ratio; > 1: ours faster).")
    print(f"Same work (evaluation excluded on both sides): ours/brax = {paired['ours_no_eval']:.2f}x; "
          f"ours with its per-epoch evaluation of {args.eval_episodes} episodes: {paired['ours']:.2f}x.")
    return add_roof({"args": dataclasses.asdict(args), "rows": rows, "ratio": paired["ours_no_eval"],
                     "ratio_with_eval": paired["ours"]}, args)


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    emitters_on_everywhere()  # both sides compile alike (timed.py)
    main(tyro.cli(Args))
