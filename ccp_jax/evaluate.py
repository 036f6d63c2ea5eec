"""Evaluate a trained run again: more episodes than an epoch's, or with the policies' training noise.

    python -m ccp_jax.evaluate RUN_DIR [--episodes 100] [--stochastic] [--epoch E] [--seed S] [--out FILE.json]

Every grid member of the run's checkpoint is evaluated on the same start states, in one vmapped
program. A training run's per-epoch success comes from a few deterministic episodes (docs/design.md#hyperparameters);
with `--stochastic` the actions are sampled as in collection, which tells a first agent that
hands over only while exploring from one that never does.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":  # the CLI: MJX's CPU flag and quiet import, before the imports below load brax and MJX
    envs_mjx.configure_cpu()

import argparse
from pathlib import Path
from typing import Optional, Sequence

import jax

from ccp_jax import outputs
from ccp_jax.collect import make_evaluate
from ccp_jax.envs import make_env
from ccp_jax.policy import load_actors


def evaluate_run(run_dir: str | Path, episodes: int = 100, stochastic: bool = False, epoch: Optional[int] = None,
                 seed: int = 0) -> list[dict]:
    """One dict per grid member: member, seed, eta, episodes, stochastic, then the evaluation fields of a
    metrics.jsonl row (`outputs.eval_fields`: success_rate, eval_return, stage_reached_mean, stage_fraction [N],
    eval_episode_length, eval_end)."""
    run_dir = Path(run_dir)
    config = outputs.read_config(run_dir)
    if config.algo == "tp":
        raise ValueError("algo: evaluate loads SAC-family actors (csac, naive, sac); a TP run's transition "
                         "policies are not supported")
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1, got {episodes}")
    actor, actors = load_actors(run_dir, config, epoch)  # leaves [G, N, ...]
    evaluate = make_evaluate(config, make_env(config), actor, episodes=episodes, stochastic=stochastic)
    metrics = jax.device_get(jax.jit(jax.vmap(evaluate, in_axes=(0, None)))(actors, jax.random.PRNGKey(seed)))
    return [{"member": member, "seed": member_seed, "eta": list(eta), "episodes": episodes, "stochastic": stochastic,
             **outputs.eval_fields(metrics, member)} for member, (eta, member_seed) in enumerate(config.members)]


def table(rows: list[dict]) -> str:
    """A markdown table of `evaluate_run`'s rows."""
    ends = sorted({k for r in rows for k in r.get("eval_end", {})})
    head = ["member", "seed", "eta", "success", "stage reached, fraction per stage"] + ends
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        cells = [str(r["member"]), str(r["seed"]), outputs.eta_text(r["eta"]), f"{r['success_rate']:.2f}",
                 " ".join(f"{f:.2f}" for f in r["stage_fraction"])]
        lines.append("| " + " | ".join(cells + [f"{r['eval_end'][k]:.2f}" for k in ends]) + " |")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> list[dict]:
    envs_mjx.configure_cpu()  # before anything starts JAX
    parser = argparse.ArgumentParser(prog="python -m ccp_jax.evaluate",
                                     description="Evaluate every grid member of a trained run from its checkpoint.")
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per member (default 100)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions as in training, not the mean")
    parser.add_argument("--epoch", type=int, help="checkpoint epoch (default: the latest)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the start states (and of the noise)")
    parser.add_argument("--out", type=Path, help="also write the rows to FILE.json")
    args = parser.parse_args(argv)
    try:
        rows = evaluate_run(args.run_dir, args.episodes, args.stochastic, args.epoch, args.seed)
    except ValueError as err:
        parser.exit(2, f"error: {err}\n")
    mode = "stochastic" if args.stochastic else "deterministic"
    print(f"{args.episodes} {mode} episodes per member, {args.run_dir}\n\n{table(rows)}")
    if args.out:
        outputs.write_json(args.out, rows)
    return rows


if __name__ == "__main__":
    main()
