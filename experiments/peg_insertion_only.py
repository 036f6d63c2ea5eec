"""Peg in hole's insertion alone, from a good grasp: can the insertion agent learn to insert on its own?

    PYTHONPATH=experiments python -m ccp_jax.train --env peg_insertion_only:make --algo naive \
        --preset small --total-steps 200000 --out runs/peg-insertion-only

A diagnostic for issue 57 (docs/peg.md), not a task of the paper: every episode starts from the peg env's
reset (the hand on C MuJoCo, `envs_mjx.peg_in_hole`), then the scripted thick-section grasp
(`scripted_action` policy 0, the grasp that can insert fully) runs until the grasp is recognised (stage 2 of
the peg task), at most `GRASP_STEPS` control steps. From there the episode is the peg task's, for
`episode_length` more steps: both stages stay (the first is done, R_1 = 1), so with ``--algo naive`` the
insertion agent (agent 2) acts from the first step and learns alone on R_2, while agent 1 never acts; with
``--algo sac`` one agent learns on R_1 + R_2. If an agent started this way learns to insert and the
two-agent runs do not, the grasp is what fails them.

`metrics["start_grasped"]` (in the rows' ``eval_end``) says whether the scripted grasp held at the start.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import State, Wrapper

from envs_mjx.peg_in_hole import PegInHole, scripted_action

GRASP_STEPS = 120  # the scripted thick grasp takes 40-80 control steps from any reset


class InsertionOnly(Wrapper):
    """The peg task, each episode starting in its insertion stage from a scripted thick-section grasp.

    The state's ``pipeline_state`` is the inner peg env's (``env``) whole `State`; observations, actions, stages and
    rewards are the peg env's (float32[41], float32[2], 2 stages); ``info["steps"]`` counts from the grasp.
    """

    num_stages = 2

    def __init__(self, episode_length: int = 300, model: str = "hand", physics: str = "c"):
        # brax's Wrapper passes on the sizes and the backend; `env` is the inner peg env
        super().__init__(PegInHole(episode_length=episode_length + GRASP_STEPS, model=model, physics=physics))
        self.episode_length = int(episode_length)

    def reset(self, rng: jax.Array) -> State:
        k_reset, k_script = jax.random.split(rng)

        def grasping(carry):
            s, t = carry
            return (s.info["stage"] < 1) & (t < GRASP_STEPS)

        def scripted(carry):
            s, t = carry
            return self.env.step(s, scripted_action(s, jnp.int32(0), k_script)), t + 1

        inner, _ = jax.lax.while_loop(grasping, scripted, (self.env.reset(k_reset), jnp.int32(0)))
        zero = jnp.float32(0.0)
        return self._wrap(inner, jnp.int32(0), zero, zero)

    def step(self, state: State, action: jax.Array) -> State:
        inner = self.env.step(state.pipeline_state, action)
        steps = state.info["steps"] + 1
        success = inner.metrics["success"]
        timeout = jnp.maximum((steps >= self.episode_length).astype(jnp.float32), inner.info["truncation"])
        return self._wrap(inner, steps, jnp.maximum(success, timeout), timeout * (1.0 - success))

    def _wrap(self, inner: State, steps: jax.Array, done: jax.Array, truncation: jax.Array) -> State:
        grasped = (inner.info["stage"] >= 1).astype(jnp.float32)
        return State(pipeline_state=inner, obs=inner.obs, reward=inner.reward, done=done,
                     metrics={"success": inner.metrics["success"], "start_grasped": grasped},
                     info={"stage": inner.info["stage"], "rewards": inner.info["rewards"], "truncation": truncation,
                           "steps": steps})

    def render_frames(self, states: State):
        """The peg env's frames of the inner states (the contract's optional render hook)."""
        return self.env.render_frames(states.pipeline_state)


def make(episode_length: int = 300) -> InsertionOnly:
    """The factory `--env peg_insertion_only:make` names (episode length: the CLI's --max-episode-steps is not
    passed to user factories, so it is this argument's default)."""
    return InsertionOnly(episode_length=episode_length)
