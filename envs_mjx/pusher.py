"""Brax's own `pusher` (a 7-joint arm pushes a puck to a goal) as a two-stage task.

The inner env is ``brax.envs.get_environment("pusher", backend=...)``, unchanged;
`StageWrapper` adds the stages. Positions come from brax's observation
(float32[23]): ``obs[14:17]`` the "fingertip" (brax's choice: the origin of
``r_wrist_flex_link``, the middle of the wrist bar whose two prongs form a
scoop), ``obs[17:20]`` the object's centre, ``obs[20:23]`` the goal. The
object (a puck of radius 5 cm, centre at z = -0.275) slides on the table; the
goal is fixed at (0.45, -0.05). Resets put the object at x in [0.25, 0.65],
y in [-0.35, -0.05], 0.17 - 0.36 m from the goal (brax samples "x" in [-0.3, 0]
but its joint order puts that sample on the y slide).

Stages (distances in m; ``d_reach`` is 3-D, ``d_goal`` in the table plane):
  0 reach: R_1 = clip(1 - (d_reach - reach_radius) / reach_scale, 0, 1) with
           d_reach = |fingertip - object|; advances when d_reach < reach_radius
           (0.12: the wrist bar touching the puck's side puts them 0.07 m apart
           with the bar level with the puck, about 0.10 m with it upright).
  1 push:  R_2 = clip(1 - (d_goal - goal_radius) / goal_scale, 0, 1) with
           d_goal = |object - goal|_xy.
  success: d_goal < goal_radius (0.05), however the puck got there (the stage then
           becomes 1 and both rewards 1); the episode ends.
Each R_n reaches 1 exactly when its subtask is achieved, so a reward never
jumps at a stage change. Reaching is measured to the object's centre from any
side; only a reach from behind (the side away from the goal) leaves the wrist
ready to push: the greedy reach is not always the good one, as in the maze.

Observation: brax's 23 values plus the stage one-hot (2); actions: the 7 joint
torques in [-1, 1] (brax scales them to its actuator range).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax import envs as brax_envs
from brax import kinematics
from brax import math as bmath
from brax.envs.base import State

from envs_mjx import warn_if_cpu_unconfigured
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
      backend: brax physics pipeline: 'mjx' (default), 'generalized', 'positional'
        or 'spring'. Steps/s of brax's pusher measured on the 2-core CPU (jitted
        lax.scan of random actions, medians of 5, interleaved), batch 1 / 64, with
        XLA_FLAGS=--xla_cpu_use_fusion_emitters=false (ccp_jax sets it): mjx
        789 / 3264, spring 555 / 2306, generalized 553 / 1804, positional 256 /
        1101. Without the flag mjx falls to 55 / 10 (and compiles in 2 min) while
        the others barely change, hence the warning below. (spring and positional also change the
        physics: 1 ms steps with 20x actuator gear, brax's own settings.)
    """

    reach_radius = 0.12
    reach_scale = 1.0  # the fingertip starts 0.4 - 0.85 m from the object
    goal_radius = 0.05
    goal_scale = 0.4  # the object starts at most 0.36 m from the goal

    def __init__(self, episode_length: int = 200, backend: str = "mjx"):
        if backend == "mjx":
            warn_if_cpu_unconfigured("Pusher(backend='mjx')", "14x (batch 1) to 300x (batch 64)")
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
            success=lambda s: goal_distance(s) < self.goal_radius,
        )
        super().__init__(inner, spec, episode_length=episode_length)


class PushPlan(NamedTuple):
    """The scripted controller's memory: phase int32[] (0 above, 1 lowered, 2 pushing),
    the pin's start point behind the puck float32[2], and the two joint postures
    float32[7] that put it there, high and low."""

    phase: jax.Array
    pre: jax.Array
    q_high: jax.Array
    q_low: jax.Array


def scripted_controller(env: Pusher, back: float = 0.13, z_high: float = -0.12, z_push: float = -0.2,
                        speed: float = 0.02, kp: float = 10.0, kd: float = 0.5
                        ) -> tuple[Callable[[State], PushPlan], Callable[[State, PushPlan], tuple[jax.Array, PushPlan]]]:
    """A hand-written policy that solves the task when the arm can get behind the puck.

    Returns ``(plan, act)``: ``plan(state) -> PushPlan`` at reset and
    ``act(state, plan) -> (action float32[7], plan)`` each step; both jit/vmap-able.

    How it pushes. Only the wrist's geoms (a bar with two prongs) collide with the
    puck, and the table collides with them too. The controller turns the bar
    upright (a vertical pin, so it meets the puck's side whatever the arm's yaw),
    the prongs pointing away from the push; its centre (brax's fingertip) kept at
    z = `z_push`, 7.5 cm above the puck's centre, is 0.10 m from it when touching
    (inside `reach_radius`).
      0: joint PD to a posture with the pin `back` m behind the puck (on the side
         away from the goal) at z = `z_high`, above the puck's reach;
      1: lower it to `z_push` (the pin's foot just above the table);
      2: carry the puck: move the pin `speed` m per step along puck -> goal, plus a
         pull that keeps it touching. The puck slides on two joints and cannot
         turn, and friction (0.8) holds it on the pin, so it goes where the pin
         goes: steering by offsetting the contact sideways does not work here.
    Postures come from damped-least-squares IK on brax's kinematics (the task: pin
    position, pin upright, prongs back), solved from 8 starting postures at reset;
    pushing uses one resolved-rate IK step per control step. Torques are joint PD,
    ``kp (q_target - q) - kd qd``, scaled by the actuator gear. Phases advance once
    the pin is in place and the arm has settled, so a fast swing cannot skip one.

    Measured: success on 18 of 24 resets with mjx, 7 of 8 with generalized, each
    by step ~80. It fails where the arm cannot put the upright pin behind the puck:
    pucks far out near the goal's y (x > ~0.6, pushed towards -x; the point behind
    is beyond the arm's 0.82 m reach, IK residual > 5 cm) and pucks close to the
    shoulder (x ~ 0.3, y ~ -0.33: the point behind is too near the base to fold
    into); rarely, the push runs out of reach 2 cm short.
    """
    model = env.env.sys
    limits = np.asarray(model.dof.limit).T[:7]
    lo, hi = jnp.asarray(limits[:, 0]), jnp.asarray(limits[:, 1])
    gear = jnp.asarray(model.actuator.gear)
    ctrl_hi = jnp.asarray(model.actuator.ctrl_range)[:, 1]
    n_q = model.q_size()
    seeds = jnp.asarray(np.concatenate([
        [[0.8, 1.2, -0.7, -1.6, -1.5, -1.0, 0.35], [1.6, 0.5, 1.0, -0.5, 0.5, -0.9, 0.3],
         [1.2, 0.4, 1.3, -0.2, -1.4, -0.4, -1.4], [0.0, 1.1, -0.9, -1.5, -1.5, -0.8, 0.4]],
        np.random.default_rng(0).uniform(limits[:, 0], limits[:, 1], (4, 7))]), jnp.float32)

    def task(q: jax.Array, u: jax.Array) -> jax.Array:
        """float32[6]: pin centre (3); bar axis x, y (0 when upright); how far the prongs point along u."""
        x, _ = kinematics.forward(model, jnp.concatenate([q, jnp.zeros(n_q - 7)]), jnp.zeros(model.qd_size()))
        bar = bmath.rotate(jnp.array([0.0, 1.0, 0.0]), x.rot[6])
        prong = bmath.rotate(jnp.array([1.0, 0.0, 0.0]), x.rot[6])
        return jnp.concatenate([x.pos[5], 0.3 * bar[:2], 0.3 * jnp.maximum(prong[:2] @ u + 0.3, 0.0)[None]])

    def ik_step(q, u, err):
        jac = jax.jacfwd(task)(q, u)
        return jnp.clip(q + jac.T @ jnp.linalg.solve(jac @ jac.T + 1e-2 * jnp.eye(6), err), lo, hi)

    def ik(target, u, q0, iters=60):
        goal = jnp.concatenate([target, jnp.zeros(3)])
        q = jax.lax.fori_loop(0, iters, lambda _, q: ik_step(q, u, goal - task(q, u)), q0)
        return q, jnp.linalg.norm(task(q, u) - goal)

    def geometry(obs):
        puck, goal = obs[OBJECT][:2], obs[GOAL][:2]
        u = (goal - puck) / jnp.linalg.norm(goal - puck)
        return puck, u, puck - back * u

    def plan(state: State) -> PushPlan:
        _, u, pre = geometry(state.obs)
        qs, errs = jax.vmap(lambda q0: ik(jnp.append(pre, z_high), u, q0))(seeds)
        q_high = qs[jnp.argmin(errs)]
        q_low, _ = ik(jnp.append(pre, z_push), u, q_high)
        return PushPlan(jnp.zeros((), jnp.int32), pre, q_high, q_low)

    def act(state: State, p: PushPlan) -> tuple[jax.Array, PushPlan]:
        obs = state.obs
        q, qd, pin = obs[:7], obs[7:14], obs[TIP]
        puck, u, _ = geometry(obs)
        settled = jnp.linalg.norm(qd) < 0.5
        off_pre = jnp.linalg.norm(pin[:2] - p.pre)
        phase = jnp.where((p.phase == 0) & (off_pre < 0.03) & settled, 1, p.phase)
        phase = jnp.where((phase == 1) & (jnp.abs(pin[2] - z_push) < 0.03) & (off_pre < 0.04) & settled, 2, phase)
        rel = puck - pin[:2]
        dist = jnp.linalg.norm(rel)
        err_xy = speed * u + 0.5 * (dist - 0.065) * rel / dist  # carry along u; stay touching
        err = jnp.concatenate([err_xy, jnp.array([z_push - pin[2]]), -task(q, u)[3:]])
        q_push = ik_step(q, u, err)
        q_target = jnp.stack([p.q_high, p.q_low, q_push])[phase]
        torque = kp * (q_target - q) - kd * qd
        action = jnp.clip(torque / (gear * ctrl_hi), -1.0, 1.0)
        return action, p._replace(phase=phase)

    return plan, act
