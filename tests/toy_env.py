"""A tiny multi-stage env for trainer tests: a point on a line crossing N unit segments.

x starts in [0, 0.2]; the action moves it by 0.25·a; stage n spans x in [n, n+1];
R_n follows docs/design.md#environments-and-their-contract (progress x − n inside the stage); success at x >= N − 0.05.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State


class Line(Env):
    def __init__(self, stages: int = 2, episode_length: int = 50, obs_size: int = 3):
        self.num_stages, self.episode_length, self._obs_size = stages, episode_length, obs_size

    @property
    def observation_size(self) -> int:
        return self._obs_size

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "jax"

    def _obs(self, x):
        return jnp.concatenate([x[None], jnp.zeros((self._obs_size - 1,))]).astype(jnp.float32)

    def _rewards(self, x, stage):
        n = jnp.arange(self.num_stages)
        progress = jnp.clip(x - n, 0.0, 1.0)
        return jnp.where(n < stage, 1.0, jnp.where(n == stage, progress, 0.0)).astype(jnp.float32)

    def reset(self, rng: jax.Array) -> State:
        x = jax.random.uniform(rng, (), minval=0.0, maxval=0.2)
        stage = jnp.int32(0)
        info = {"stage": stage, "rewards": self._rewards(x, stage), "truncation": jnp.float32(0),
                "steps": jnp.int32(0)}
        return State(pipeline_state=x, obs=self._obs(x), reward=info["rewards"].sum(), done=jnp.float32(0),
                     metrics={"success": jnp.float32(0)}, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        x = jnp.clip(state.pipeline_state + 0.25 * jnp.clip(action[0], -1, 1), 0.0, float(self.num_stages))
        stage = jnp.maximum(state.info["stage"], jnp.clip(jnp.floor(x), 0, self.num_stages - 1).astype(jnp.int32))
        success = (x >= self.num_stages - 0.05).astype(jnp.float32)
        rewards = jnp.where(success > 0, 1.0, self._rewards(x, stage))
        steps = state.info["steps"] + 1
        timeout = (steps >= self.episode_length).astype(jnp.float32)
        done = jnp.maximum(success, timeout)
        info = {"stage": stage, "rewards": rewards, "truncation": timeout * (1 - success), "steps": steps}
        return State(pipeline_state=x, obs=self._obs(x), reward=rewards.sum(), done=done,
                     metrics={"success": success}, info=info)
