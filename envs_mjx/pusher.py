"""Brax's own `pusher` (a 7-joint arm pushes a puck to a goal) as a two-stage task.

The inner env is ``brax.envs.get_environment("pusher", backend=...)``, unchanged;
`StageWrapper` adds the stages. Positions come from brax's observation
(float32[23]): ``obs[14:17]`` the "fingertip" (brax's choice: the origin of
``r_wrist_flex_link``, the middle of the wrist bar whose two prongs form a
scoop), ``obs[17:20]`` the object's centre, ``obs[20:23]`` the goal. The
object (a puck of radius 5 cm, z = -0.275) slides on the table; the goal is
fixed at (0.45, -0.05); resets put the object 0.17 - 0.39 m from it.

Stages (distances in m; ``d_reach`` is 3-D, ``d_goal`` in the table plane):
  0 reach: R_1 = clip(1 - (d_reach - reach_radius) / reach_scale, 0, 1) with
           d_reach = |fingertip - object|; advances when d_reach < reach_radius
           (0.09: the bar against the puck puts them 0.07 apart).
  1 push:  R_2 = clip(1 - (d_goal - goal_radius) / goal_scale, 0, 1) with
           d_goal = |object - goal|_xy.
  success: d_goal < goal_radius (0.05) while in stage 1; the episode ends.
Each R_n reaches 1 exactly when its subtask is achieved, so a reward never
jumps at a stage change. Reaching is measured to the object's centre from any
side; only a reach from behind (the side away from the goal) leaves the scoop
ready to push — the greedy reach is not always the good one, as in the maze.

Observation: brax's 23 values plus the stage one-hot (2); actions: the 7 joint
torques in [-1, 1] (brax scales them to its actuator range).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from brax import envs as brax_envs
from brax.envs.base import State

from envs_mjx.stage_wrapper import StageSpec, StageWrapper

TIP, OBJECT, GOAL = slice(14, 17), slice(17, 20), slice(20, 23)


def reach_distance(state: State) -> jax.Array:
    """float32[]: 3-D distance from brax's fingertip to the object's centre."""
    return jnp.linalg.norm(state.obs[TIP] - state.obs[OBJECT])


def goal_distance(state: State) -> jax.Array:
    """float32[]: distance from the object to the goal in the table plane (their heights differ by design)."""
    return jnp.linalg.norm(state.obs[OBJECT][:2] - state.obs[GOAL][:2])


class Pusher(StageWrapper):
    """Reach the puck, then push it to the goal; two stages (see the module docstring).

    Args:
      episode_length: steps of dt = 0.05 s before truncation.
      backend: brax physics pipeline: 'mjx' (default; fastest measured on CPU),
        'generalized', 'positional' or 'spring'.
    """

    reach_radius = 0.09
    reach_scale = 1.0  # the fingertip starts about 0.8 m from the object
    goal_radius = 0.05
    goal_scale = 0.4  # the largest start distance of the object from the goal is about 0.39 m

    def __init__(self, episode_length: int = 200, backend: str = "mjx"):
        inner = brax_envs.get_environment("pusher", backend=backend)
        spec = StageSpec(
            num_stages=2,
            progress=(
                lambda s: 1.0 - (reach_distance(s) - self.reach_radius) / self.reach_scale,
                lambda s: 1.0 - (goal_distance(s) - self.goal_radius) / self.goal_scale,
            ),
            completed=(
                lambda s: reach_distance(s) < self.reach_radius,
                lambda s: goal_distance(s) < self.goal_radius,
            ),
        )
        super().__init__(inner, spec, episode_length=episode_length)
