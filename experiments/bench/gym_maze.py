"""A Gymnasium view of our Maze (envs_mjx.maze), for single-env libraries such as stable-baselines3.

    from gym_maze import GymMaze
    env = GymMaze(rooms=2)
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

It steps the very same pure JAX env (one jitted `reset` and one jitted `step`,
compiled once per process), so a library driving it sees exactly our dynamics:

* observation: float32[24] (laser scan, position, heading; see envs_mjx.maze);
* action: float32[2] in [-1, 1];
* reward: Σ_n R_n, the whole-task reward (what end-to-end SAC optimises);
* terminated: the goal was reached (success; the only true termination);
* truncated: the episode hit `episode_length` steps without success;
* info: `stage` (0-based U(s)), `rewards` (float32[N], subtask rewards), `success`.

Each call crosses the Python/JAX boundary once (tens of microseconds on CPU);
that is the cost a host-driven library pays per env step and is part of what
the benchmarks measure.
"""
from __future__ import annotations

from typing import Any, Optional

import gymnasium as gym
import jax
import numpy as np

from envs_mjx.maze import Maze


class GymMaze(gym.Env):
    """`gymnasium.Env` over `envs_mjx.maze.Maze(rooms, episode_length)`.

    Args:
      rooms: number of rooms (= stages) N >= 1.
      episode_length: steps after which an episode is truncated.
    """

    metadata = {"render_modes": []}

    def __init__(self, rooms: int = 2, episode_length: int = 1000):
        self.maze = Maze(rooms=rooms, episode_length=episode_length)
        # Scan and position are normalised to [0, 1], heading is (cos, sin).
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (self.maze.observation_size,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (self.maze.action_size,), np.float32)
        self._reset = jax.jit(self.maze.reset)
        self._step = jax.jit(self.maze.step)
        self._key = jax.random.PRNGKey(0)
        self._state = None

    @property
    def num_stages(self) -> int:
        return self.maze.num_stages

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        self._key, key = jax.random.split(self._key)
        self._state = self._reset(key)
        return np.asarray(self._state.obs), self._info(self._state)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        self._state = self._step(self._state, np.asarray(action, np.float32))
        s = jax.device_get(self._state)
        success = bool(s.metrics["success"] > 0)
        truncated = bool(s.info["truncation"] > 0)
        return np.asarray(s.obs), float(s.reward), success, truncated, self._info(s)

    @staticmethod
    def _info(state) -> dict:
        return {"stage": int(state.info["stage"]), "rewards": np.asarray(state.info["rewards"]),
                "success": float(state.metrics["success"])}
