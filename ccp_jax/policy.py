"""Trained policies for use outside training."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp

from ccp_jax import checkpoint, outputs
from ccp_jax.collect import agent_of, policy_mean_and_log_std
from ccp_jax.config import Config
from ccp_jax.envs import make_env
from ccp_jax.networks import Actor, deterministic_action
from ccp_jax.grid import make_grid_train


def load_actors(run_dir: str | Path, config: Config, epoch: int | None = None) -> tuple[Actor, Any]:
    """The actor module of the run `config` describes and its checkpointed parameters for every member
    (leaves [G, N, ...]; the latest checkpoint unless `epoch`), without reading the replay buffers."""
    trainer = make_grid_train(config, make_env(config), jax.devices()[:1])
    abstract = trainer.abstract_state(config.grid_arrays()[1]).agents.actor
    mngr = checkpoint.manager(Path(run_dir))
    try:
        _, actors = checkpoint.restore(mngr, abstract, item="policy", grid_size=config.grid_size, epoch=epoch)
    finally:
        mngr.close()
    return trainer.networks.actor, actors


def load_member(run_dir: str | Path, member: int = 0, epoch: int | None = None) -> tuple[Config, Actor, Any]:
    """(config, actor module, member `member`'s actor parameters, leaves [N, ...]) from a run folder's checkpoint
    (the latest unless `epoch`); a member outside the grid is a ValueError naming `member`."""
    run_dir = Path(run_dir)
    config = outputs.read_config(run_dir)
    if not 0 <= member < config.grid_size:
        raise ValueError(f"member: the run has members 0..{config.grid_size - 1}, got {member}")
    actor, actors = load_actors(run_dir, config, epoch)
    return config, actor, jax.tree.map(lambda x: x[member], actors)


def chain_policy(config: Config, actor: Actor, params: Any) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """policy(obs [b, obs_size], stage [b]) -> action [b, action_size]: the deterministic action (tanh of the mean)
    of the agent acting in each stage, with one member's actor `params` (leaves [N, ...]) inside."""

    def policy(obs: jax.Array, stage: jax.Array) -> jax.Array:
        mean, _ = policy_mean_and_log_std(actor, params, obs, agent_of(config, stage.astype(jnp.int32)))
        return deterministic_action(mean)

    return policy


def load_policy(run_dir: str | Path, member: int = 0, epoch: int | None = None) -> Callable:
    """The deterministic policy of grid member `member` from a run folder's checkpoint.

    Returns a jitted `policy(obs, stage) -> action`: obs float32[..., obs_size],
    stage int32[...] (the env's `state.info["stage"]`); the acting agent is the
    stage's own (or the single agent of end-to-end SAC). Uses the latest
    checkpoint unless `epoch` is given.
    """
    chain = chain_policy(*load_member(run_dir, member, epoch))

    @jax.jit
    def policy(obs: jax.Array, stage: jax.Array) -> jax.Array:
        batch_shape = stage.shape
        return chain(obs.reshape(-1, obs.shape[-1]), stage.reshape(-1)).reshape(batch_shape + (-1,))

    return policy
