"""Builds the environment a `Config` names. Imports env modules lazily."""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from brax.envs.base import Env

    from ccp_jax.config import Config

ENV_NAMES = ("maze", "peg", "pusher")
# Envs whose number of stages does not depend on the `rooms` setting.
FIXED_STAGES = {"peg": 2, "pusher": 2}


def make_env(config: "Config") -> "Env":
    """The env of `config.task.env`: a built-in name or 'module.path:factory'."""
    if config.task.env == "maze":
        from envs_mjx.maze import Maze

        return Maze(rooms=config.task.rooms, episode_length=config.task.max_episode_steps,
                    reverse=config.ablations.maze_reverse, slide=config.ablations.maze_slide)
    if config.task.env == "peg":
        from envs_mjx.peg_in_hole import PegInHole

        return PegInHole(episode_length=config.task.max_episode_steps, model=config.task.peg_model,
                         physics=config.task.peg_physics, grip_held=config.ablations.peg_grip_held)
    if config.task.env == "pusher":
        from envs_mjx.pusher import Pusher

        return Pusher(episode_length=config.task.max_episode_steps)
    return user_env(config.task.env)


def user_env(spec: str, check: bool = False) -> "Env":
    """The env a user's 'module.path:factory' returns; with `check`, refused unless it meets the contract.

    Failures raise `ConfigError` on the field "env", before anything of the
    trainer is compiled (`check_env` jits only the env's own reset and step).
    """
    from ccp_jax.config import ConfigError

    module_name, _, factory = spec.partition(":")
    try:
        make = getattr(importlib.import_module(module_name), factory)
    except ImportError as err:
        raise ConfigError("env", f"cannot import {module_name!r} for {spec!r}: {err}") from None
    except AttributeError:
        raise ConfigError("env", f"module {module_name!r} has no factory {factory!r}") from None
    if not callable(make):
        raise ConfigError("env", f"{spec!r}: {module_name}.{factory} is a {type(make).__name__}, not a factory; "
                                 "name a function (or class) that takes no arguments and returns the env")
    try:
        env = make()
    except Exception as err:  # the user's code: say whose it is, keep its traceback as the cause
        raise ConfigError("env", f"the factory {spec!r} raised {type(err).__name__}: {err}") from err
    if check:
        from envs_mjx.contract import EnvContractError, check_env

        try:
            check_env(env)
        except EnvContractError as err:
            raise ConfigError("env", f"{spec} is refused: {err}") from None
    return env
