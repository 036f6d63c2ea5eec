"""Command line and Python entry point: train a whole grid of runs in one program.

    python -m ccp_jax.train --env maze --rooms 3 --algo csac --eta 0.1 0.5 0.9 --seeds 5 --out runs/x

The host loop below only logs, shows progress and saves; each epoch of every
grid member is one call of the compiled, vmapped `train_step`.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Literal, Optional

import jax
import jax.numpy as jnp
import numpy as np
import tyro
from tqdm.auto import tqdm

from ccp_jax import outputs
from ccp_jax.config import Config, ConfigError, PresetName, make_config
from ccp_jax.envs import make_env
from ccp_jax.trainer import make_grid_train


@dataclasses.dataclass
class Args:
    """Train CSAC (or a baseline) on a multi-stage task; every ratio × seed in one vmapped program."""

    env: str = "maze"
    """Environment: maze, peg, or 'module.path:factory' returning an env that meets the contract."""
    rooms: int = 2
    """Number of maze rooms (stages)."""
    algo: Literal["csac", "naive", "sac"] = "csac"
    """csac: cooperative agents; naive: independent agents; sac: one end-to-end agent."""
    eta: Optional[tuple[float, ...]] = None
    """Grid of shared cooperative ratios in [0, 1] (default 0.1)."""
    eta_per_agent: Optional[tuple[str, ...]] = None
    """Grid of per-agent ratio vectors, each 'A,B,...' with one value per cooperative agent (rooms − 1)."""
    seeds: int = 1
    """Seeds per ratio: 0 .. seeds−1 (shifted by --first-seed)."""
    first_seed: int = 0
    preset: PresetName = "small"
    """paper: the paper's sizes; small: [64, 64] nets (SPEC §7); tiny: seconds-scale, for tests."""
    total_steps: Optional[int] = None
    """Environment steps per run (default: the preset's)."""
    out: Optional[Path] = None
    """Run folder (default runs/<env>-<algo>-<time>); must not already hold a run."""
    num_envs: Optional[int] = None
    hidden: Optional[tuple[int, ...]] = None
    batch_size: Optional[int] = None
    buffer_size: Optional[int] = None
    steps_per_epoch: Optional[int] = None
    train_loops_per_epoch: Optional[int] = None
    eval_episodes: Optional[int] = None
    max_episode_steps: Optional[int] = None
    gamma: Optional[float] = None
    progress: bool = True
    """Show a progress bar."""


def parse_eta_vector(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise ConfigError("eta_per_agent", f"cannot read {text!r}; write ratios as 'A,B' (e.g. 0.1,1.0)") from None


def config_from_args(args: Args) -> Config:
    """The validated `Config` the arguments describe (raises `ConfigError` naming the field)."""
    if args.seeds < 1:
        raise ConfigError("seeds", f"must be >= 1, got {args.seeds}")
    if args.eta is not None and args.eta_per_agent is not None:
        raise ConfigError("eta", "give either --eta or --eta-per-agent, not both")
    if args.eta_per_agent is not None:
        etas = tuple(parse_eta_vector(t) for t in args.eta_per_agent)
    else:
        etas = tuple((x,) for x in (args.eta or (0.1,)))
    overrides = {k: getattr(args, k) for k in ("total_steps", "num_envs", "hidden", "batch_size", "buffer_size",
                                               "steps_per_epoch", "train_loops_per_epoch", "eval_episodes",
                                               "max_episode_steps", "gamma") if getattr(args, k) is not None}
    rooms = args.rooms
    if ":" in args.env:  # a user's env decides its own number of stages
        rooms = make_env(make_config(args.preset, env=args.env)).num_stages
    return make_config(args.preset, env=args.env, rooms=rooms, algo=args.algo, etas=etas,
                       seeds=tuple(range(args.first_seed, args.first_seed + args.seeds)), **overrides)


def prepare_out(out: Optional[Path], config: Config) -> Path:
    """Creates the run folder; refuses one that already holds a run, so nothing is overwritten."""
    if out is None:
        out = Path("runs") / f"{config.env.replace(':', '_')}-{config.algo}-{time.strftime('%Y%m%d-%H%M%S')}"
    if (out / "config.json").exists() or (out / "metrics.jsonl").exists():
        raise ConfigError("out", f"{out} already holds a run; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    return out


def run(config: Config, out: Path, progress: bool = True) -> dict:
    """Trains the grid of `config`, writing config.json, metrics.jsonl and summary.json to `out`.

    Returns the summary (per member: final success = mean of the last 10 epochs).
    """
    env = make_env(config)
    trainer = make_grid_train(config, env)
    outputs.write_json(out / "config.json", config.to_dict())
    metrics_path = out / "metrics.jsonl"
    eta, seed = config.grid_arrays()
    eta = jnp.asarray(eta)

    start = time.time()
    state = trainer.init(jnp.asarray(seed))
    rows: list[dict] = []
    bar = tqdm(range(config.num_epochs), desc=f"{config.algo} {config.env} x{config.grid_size}",
               unit="epoch", disable=not progress, dynamic_ncols=True)
    for epoch in bar:
        t0 = time.time()
        state, metrics = trainer.train_step(state, eta)
        metrics = jax.device_get(metrics)
        epoch_rows = outputs.metric_rows(config, epoch + 1, metrics, time.time() - t0)
        outputs.append_rows(metrics_path, epoch_rows)
        rows.extend(epoch_rows)
        success = np.asarray(metrics.eval.success_rate)
        bar.set_postfix(steps=f"{int(metrics.env_steps.max()):,}", best_success=f"{success.max():.2f}",
                        mean_success=f"{success.mean():.2f}")
    summary = outputs.summarise(config, rows, wall_s=time.time() - start)
    outputs.write_json(out / "summary.json", summary)
    return summary


def main(argv: Optional[list[str]] = None) -> dict:
    args = tyro.cli(Args, args=argv)
    config = config_from_args(args)
    out = prepare_out(args.out, config)
    print(f"Training {config.grid_size} run(s) of {config.algo} on {config.env} "
          f"({config.num_stages} stages, {config.num_epochs} epochs of {config.steps_per_epoch} steps) -> {out}")
    summary = run(config, out, progress=args.progress)
    print(outputs.summary_table(summary))
    print(f"wall time {summary['wall_s']:.0f} s; files in {out}")
    return summary


def cli() -> None:
    """Console entry: bad input ends with one line naming the field, no traceback."""
    try:
        main()
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    cli()
