"""Builds the environment a `Config` names. Imports env modules lazily."""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from brax.envs.base import Env

    from ccp_jax.config import Config

ENV_NAMES = ("maze", "peg", "pusher")
# Envs whose number of stages does not depend on `Config.rooms`.
FIXED_STAGES = {"peg": 2, "pusher": 2}


def make_env(config: "Config") -> "Env":
    """The env of `config.env`: a built-in name or 'module.path:factory'."""
    if config.env == "maze":
        from envs_mjx.maze import Maze

        return Maze(rooms=config.rooms, episode_length=config.max_episode_steps)
    if config.env == "peg":
        from envs_mjx.peg_in_hole import PegInHole

        return PegInHole(episode_length=config.max_episode_steps)
    if config.env == "pusher":
        from envs_mjx.pusher import Pusher

        return Pusher(episode_length=config.max_episode_steps)
    module_name, _, factory = config.env.partition(":")
    return getattr(importlib.import_module(module_name), factory)()
