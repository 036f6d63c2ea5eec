"""The frozen primitives of a TP run: the deterministic per-stage agents of a finished naive run.

TP trains its primitives once and reuses them (Lee et al.; the CCP paper did
the same): train them with `--algo naive`, then point `--primitives` at that
run folder (`--primitives-member` picks the grid member). Everything here is
checked before anything compiles and fails with a `ConfigError` on the field
`primitives` (or `primitives_member`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import jax

from ccp_jax import checkpoint, outputs
from ccp_jax.config import ENV_OPTIONS, Config, ConfigError
from ccp_jax.networks import Actor
from ccp_jax.policy import load_actors


class Primitives(NamedTuple):
    actor: Actor  # the naive run's actor module
    params: Any  # its parameters, leaves [N, ...] (one agent per stage)


def primitives_config(config: Config) -> Config:
    """The naive run's config, checked against `config` (same env and stages, one agent per stage)."""
    if config.tp.primitives is None:
        raise ConfigError("primitives", "--algo tp needs frozen primitives: train them first with --algo naive "
                                        "(same env and rooms), then pass that run folder as --primitives DIR")
    run_dir = Path(config.tp.primitives)
    if not (run_dir / "config.json").exists():
        raise ConfigError("primitives", f"{run_dir} holds no run (no config.json); train the primitives with "
                                        "--algo naive --out DIR first")
    try:
        saved = outputs.read_config(run_dir, field="primitives")
    except ConfigError as err:  # a config.json that reads but does not validate names its own field
        raise ConfigError("primitives", f"{run_dir / 'config.json'} is unreadable: {err}") from None
    if saved.algo != "naive":
        raise ConfigError("primitives", f"{run_dir} is a {saved.algo!r} run; primitives come from an --algo naive run")
    if saved.task.env != config.task.env or saved.num_stages != config.num_stages:
        raise ConfigError("primitives", f"{run_dir} was trained on {saved.task.env} with {saved.num_stages} stages; "
                                        f"this run is {config.task.env} with {config.num_stages} stages")
    theirs, ours = saved.flat(), config.flat()
    for name in ENV_OPTIONS.get(config.task.env, ()):  # primitives of another robot or physics act on another task
        if theirs[name] != ours[name]:
            raise ConfigError(name, f"{run_dir} was trained with {name} = {theirs[name]}, this run has {ours[name]}")
    if not 0 <= config.tp.primitives_member < saved.grid_size:
        raise ConfigError("primitives_member", f"{run_dir} has members 0..{saved.grid_size - 1}, "
                                               f"got {config.tp.primitives_member}")
    if not (run_dir / checkpoint.CHECKPOINT_DIR).is_dir():
        raise ConfigError("primitives", f"{run_dir} has no checkpoints/ (unfinished, or copied without them)")
    return saved


def load_primitives(config: Config) -> Primitives:
    """The actor parameters of member `config.tp.primitives_member` of the naive run in `config.tp.primitives`."""
    saved = primitives_config(config)
    actor, actors = load_actors(config.tp.primitives, saved)
    params = jax.tree.map(lambda x: jax.device_get(x[config.tp.primitives_member]), actors)
    return Primitives(actor=actor, params=params)
