"""Gymnasium views of any env that meets the contract: one env (`GymEnv`) and a vmapped batch (`GymVectorEnv`).

    from envs_mjx.gym import GymEnv, GymVectorEnv
    from envs_mjx.maze import Maze
    env = GymEnv(Maze(rooms=3))                       # a gymnasium.Env
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    envs = GymVectorEnv(Maze(rooms=3), num_envs=64)   # a gymnasium.vector.VectorEnv, one jitted step for all

Both step the very same pure JAX env (jitted once per process), so a library
driving them sees exactly the dynamics the trainer learns on:

* observation: float32[observation_size]; action: float32[action_size] in [-1, 1];
* reward: Σ_n R_n, the whole task's reward (what end-to-end SAC optimises);
* terminated: the env ended the episode (success, or a failure the env ends on);
  truncated: the time limit (`episode_length`) ended it, which is not a termination;
* info: `stage` (the 0-based stage U(s)), `rewards` (float32[N], the subtask
  rewards, for a library that trains one agent per stage) and `success`.

`GymVectorEnv` resets a finished sub-env in the same step (gymnasium's
`AutoresetMode.SAME_STEP`): the observation returned is the new episode's, and
`info["final_obs"]` / `info["final_info"]` (masked by `info["_final_obs"]`)
hold the finished one's. `register()` adds the built-in tasks to gymnasium's
registry (`gymnasium.make("ccp/Maze3-v0")`). Gymnasium is an optional
dependency: `pip install "ccp-jax[gym]"`.
"""
from __future__ import annotations

from typing import Any, Optional

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from gymnasium.vector import AutoresetMode, VectorEnv


def _info(state: State) -> dict:
    """The per-stage view of a state (leaves with or without a batch axis)."""
    return {"stage": np.asarray(state.info["stage"]), "rewards": np.asarray(state.info["rewards"]),
            "success": np.asarray(state.metrics["success"])}


def _spaces(env: Env) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    obs = gym.spaces.Box(-np.inf, np.inf, (env.observation_size,), np.float32)
    act = gym.spaces.Box(-1.0, 1.0, (env.action_size,), np.float32)
    return obs, act


class GymEnv(gym.Env):
    """`gymnasium.Env` over one contract env `env` (see the module docstring for what it returns)."""

    metadata = {"render_modes": []}

    def __init__(self, env: Env):
        self.env = env
        self.observation_space, self.action_space = _spaces(env)
        self._reset = jax.jit(env.reset)
        self._step = jax.jit(env.step)
        self._key = jax.random.key(0)
        self._state: Optional[State] = None

    @property
    def num_stages(self) -> int:
        return self.env.num_stages

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.key(seed)
        self._key, key = jax.random.split(self._key)
        self._state = self._reset(key)
        return np.asarray(self._state.obs), self._scalar_info(self._state)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._state = self._step(self._state, jnp.asarray(action, jnp.float32))
        s = jax.device_get(self._state)
        truncated = bool(s.info["truncation"] > 0)
        terminated = bool(s.done > 0) and not truncated
        return np.asarray(s.obs), float(s.reward), terminated, truncated, self._scalar_info(s)

    @staticmethod
    def _scalar_info(state: State) -> dict:
        info = _info(jax.device_get(state))
        return {"stage": int(info["stage"]), "rewards": info["rewards"], "success": float(info["success"])}


class GymVectorEnv(VectorEnv):
    """`gymnasium.vector.VectorEnv` of `num_envs` copies of `env`, stepped by one jitted, vmapped step.

    A finished copy is reset within the same step (AutoresetMode.SAME_STEP).
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, env: Env, num_envs: int):
        if num_envs < 1:
            raise ValueError(f"num_envs: must be at least 1, got {num_envs}")
        self.env, self.num_envs = env, num_envs
        self.single_observation_space, self.single_action_space = _spaces(env)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self._reset = jax.jit(jax.vmap(env.reset))
        self._step = jax.jit(self._step_and_reset)
        self._key = jax.random.key(0)
        self._state: Optional[State] = None

    def _step_and_reset(self, state: State, action: jax.Array, key: jax.Array) -> tuple[State, State]:
        """(the stepped states, the states returned: a fresh episode's where the stepped one is done)."""
        stepped = jax.vmap(self.env.step)(state, action)
        fresh = jax.vmap(self.env.reset)(jax.random.split(key, self.num_envs))
        done = stepped.done > 0

        def pick(a, b):
            return jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)), a, b)

        return stepped, jax.tree.map(pick, fresh, stepped)

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        if seed is not None:
            self._key = jax.random.key(seed)
        self._key, key = jax.random.split(self._key)
        self._state = self._reset(jax.random.split(key, self.num_envs))
        return np.asarray(self._state.obs), _info(self._state)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._key, key = jax.random.split(self._key)
        stepped, self._state = self._step(self._state, jnp.asarray(actions, jnp.float32), key)
        s = jax.device_get(stepped)
        truncated = np.asarray(s.info["truncation"] > 0)
        done = np.asarray(s.done > 0)
        info = _info(jax.device_get(self._state))
        if done.any():
            info.update(final_obs=np.where(done[:, None], np.asarray(s.obs), np.nan), _final_obs=done,
                        final_info=_info(s), _final_info=done)
        return (np.asarray(self._state.obs), np.asarray(s.reward, np.float32), done & ~truncated, truncated, info)


def register() -> None:
    """Registers the built-in tasks with gymnasium: ccp/Maze2-v0, ccp/Maze3-v0, ccp/Maze4-v0, ccp/PegInHole-v0,
    ccp/Pusher-v0 (each `gymnasium.make(name, episode_length=...)`-able). Idempotent."""
    for rooms in (2, 3, 4):
        _register(f"ccp/Maze{rooms}-v0", "envs_mjx.maze:Maze", rooms=rooms)
    _register("ccp/PegInHole-v0", "envs_mjx.peg_in_hole:PegInHole")
    _register("ccp/Pusher-v0", "envs_mjx.pusher:Pusher")


def _register(name: str, factory: str, **kwargs) -> None:
    if name not in gym.registry:
        gym.register(name, entry_point=_gym_entry, kwargs=dict(factory=factory, **kwargs))


def _gym_entry(factory: str, **kwargs) -> GymEnv:
    import importlib

    module, _, attr = factory.partition(":")
    return GymEnv(getattr(importlib.import_module(module), attr)(**kwargs))
