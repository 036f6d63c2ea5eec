"""Turn any `brax.envs.base.Env` into a multi-stage env that meets the contract of `envs_mjx`.

A user describes the stages in a few lines; the wrapper does the bookkeeping
(monotone stage, subtask rewards, success, time limit, truncation)::

    spec = StageSpec(
        num_stages=2,
        progress=(lambda s: 1 - dist_a(s), lambda s: 1 - dist_b(s)),   # each float32[], clipped to [0, 1]
        completed=(lambda s: dist_a(s) < 0.05, lambda s: dist_b(s) < 0.05),
    )
    env = StageWrapper(inner_env, spec, episode_length=200)

`progress` and `completed` take the *inner* env's `State` (so `s.obs`,
`s.pipeline_state`, `s.info` are all available) and are given either as one
tuple entry per stage or as a single function `f(state, stage)` of the stage
index (an int32 scalar). Per step, with U the stage before the step:

* U advances while the completion condition of the current stage holds
  (several stages may complete in one step), never past N - 1 and never back;
* R_n = 1 for n < U, clip(progress_n, 0, 1) for n = U, 0 for n > U;
* success (by default: the last stage's completion condition holds in the last
  stage) sets every R_n to 1 and the stage to N - 1, and ends the episode;
* the episode also ends at ``episode_length`` steps (truncation, not a
  termination) or when the inner env sets ``done`` (a termination, unless the
  inner env marks it ``info["truncation"]``).

The inner env's own reward is ignored (kept in ``info["inner"]["reward"]``).
Give the raw env, not one from ``brax.envs.create`` (whose episode and
auto-reset wrappers would fight this one's).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional, Sequence, Union

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State

StageFn = Callable[[State, jax.Array], jax.Array]
"""f(inner_state, stage int32[]) -> a value for that stage."""
StateFn = Callable[[State], jax.Array]
"""f(inner_state) -> a value."""


@dataclasses.dataclass(frozen=True)
class StageSpec:
    """What the stages of a task are, on top of an inner env.

    Attributes:
      num_stages: N >= 1.
      progress: the current stage's progress in [0, 1] (clipped), float32[]; either
        `f(state, stage)` or a sequence of N functions `f_n(state)`.
      completed: whether the current stage's subtask is achieved (bool[]); same two
        forms as `progress`. The stage advances when it holds.
      success: `f(state) -> bool[]`, the whole task is done; None: the last stage's
        `completed` while in the last stage.
    """

    num_stages: int
    progress: Union[StageFn, Sequence[StateFn]]
    completed: Union[StageFn, Sequence[StateFn]]
    success: Optional[StateFn] = None

    def __post_init__(self):
        if isinstance(self.num_stages, bool) or not isinstance(self.num_stages, int) or self.num_stages < 1:
            raise ValueError(f"num_stages must be an int >= 1, got {self.num_stages!r}")
        for name in ("progress", "completed"):
            fns = getattr(self, name)
            if not callable(fns) and len(fns) != self.num_stages:
                raise ValueError(f"{name} has {len(fns)} functions, expected num_stages={self.num_stages}")

    def per_stage(self, name: str, state: State) -> jax.Array:
        """`progress` or `completed` of every stage at `state`, stacked: [N]."""
        fns = getattr(self, name)
        if callable(fns):
            # A concrete int32 per stage, so user code may branch or index on it in Python.
            values = [fns(state, jnp.int32(n)) for n in range(self.num_stages)]
        else:
            values = [f(state) for f in fns]
        return jnp.stack([jnp.asarray(v).reshape(()) for v in values])


class StageWrapper(Env):
    """A contract env (see `envs_mjx`) from an inner `brax.envs.base.Env` and a `StageSpec`.

    Observation: the inner obs (float32[O]), followed by the stage one-hot
    (float32[N]) when `stage_in_obs` — the subtask rewards depend on the stage,
    which the inner obs alone may not reveal (R_1 stays 1 after leaving its goal).

    State layout: ``pipeline_state`` is the inner one (renderers keep working);
    ``info`` holds stage int32[], rewards float32[N], truncation float32[],
    steps int32[] and ``inner`` (the inner State's reward, done, metrics, info);
    ``metrics`` holds success float32[].
    """

    def __init__(self, env: Env, spec: StageSpec, episode_length: int = 1000, stage_in_obs: bool = True):
        if isinstance(episode_length, bool) or not isinstance(episode_length, int) or episode_length < 1:
            raise ValueError(f"episode_length must be an int >= 1, got {episode_length!r}")
        self.env, self.spec = env, spec
        self.episode_length, self.stage_in_obs = episode_length, stage_in_obs
        # Traced, not run: brax's PipelineEnv.observation_size runs an eager reset (~20 s on MJX).
        obs = jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs
        if not hasattr(obs, "shape") or len(obs.shape) != 1:
            raise ValueError(f"the inner env's observation must be a flat vector, got {obs}")
        self._inner_obs_size = int(obs.shape[0])

    @property
    def num_stages(self) -> int:
        return self.spec.num_stages

    @property
    def observation_size(self) -> int:
        return self._inner_obs_size + (self.num_stages if self.stage_in_obs else 0)

    @property
    def action_size(self) -> int:
        return self.env.action_size

    @property
    def backend(self) -> str:
        return self.env.backend

    @property
    def unwrapped(self) -> Env:
        return self.env.unwrapped

    @property
    def render_frames(self) -> Callable[[State], Any]:
        """The contract's render hook (`envs_mjx.frames`) where the inner env can be drawn: its own `render_frames`
        (given the inner states), else MuJoCo frames of a brax inner env's model (`env.sys.mj_model`, free camera,
        uint8[T, 240, 320, 3]). Otherwise an AttributeError, so `hasattr(wrapper, "render_frames")` tells."""
        inner_hook = getattr(self.env, "render_frames", None)
        if inner_hook is not None:
            return lambda states: inner_hook(self._inner_stacked(states))
        model = getattr(getattr(self.env, "sys", None), "mj_model", None)
        if model is None:
            raise AttributeError(f"{type(self.env).__name__} (inside StageWrapper) has no render_frames and no MuJoCo "
                                 "model to draw")

        def draw(states: State) -> Any:
            from envs_mjx.frames import mujoco_frames  # local: only videos draw

            return mujoco_frames(model, states.pipeline_state.q)

        return draw

    def _inner_stacked(self, states: State) -> State:
        """The inner env's States of one episode, from its stacked `states` (leaves [T, ...])."""
        keep: dict[str, Any] = states.info["inner"]
        obs = states.obs[..., : self._inner_obs_size]
        return State(pipeline_state=states.pipeline_state, obs=obs, reward=keep["reward"], done=keep["done"],
                     metrics=dict(keep["metrics"]), info=dict(keep["info"]))

    def reset(self, rng: jax.Array) -> State:
        """Step 0: the inner reset, with the stage advanced past subtasks already achieved."""
        inner = self.env.reset(rng)
        stage = self._advance(inner, jnp.zeros((), jnp.int32))
        # No success at step 0: an episode that is over before its first action teaches nothing.
        return self._outer(inner, stage, jnp.zeros((), bool), jnp.zeros((), jnp.int32), jnp.zeros((), bool))

    def step(self, state: State, action: jax.Array) -> State:
        """One inner step with `action` float32[A] (clipped to [-1, 1])."""
        inner = self._inner(state)
        inner = self.env.step(inner, jnp.clip(action, -1.0, 1.0))
        stage = self._advance(inner, state.info["stage"])
        if self.spec.success is None:
            last = self.num_stages - 1
            success = (stage == last) & self.spec.per_stage("completed", inner)[last].astype(bool)
        else:
            success = jnp.asarray(self.spec.success(inner)).reshape(()).astype(bool)
        stage = jnp.where(success, self.num_stages - 1, stage)  # the whole task done completes every stage
        inner_done = inner.done > 0
        # The inner env's end is a termination unless it says it was a time limit of its own.
        inner_trunc = inner_done & (jnp.asarray(inner.info.get("truncation", 0.0)) > 0)
        terminated = success | (inner_done & ~inner_trunc)
        steps = state.info["steps"] + 1
        truncated = ((steps >= self.episode_length) | inner_trunc) & ~terminated
        return self._outer(inner, stage, success, steps, terminated | truncated, truncated)

    def _advance(self, inner: State, stage: jax.Array) -> jax.Array:
        """The stage after completing as many consecutive subtasks from `stage` as hold at `inner`."""
        done = self.spec.per_stage("completed", inner).astype(bool)
        for _ in range(self.num_stages - 1):
            stage = jnp.where((stage < self.num_stages - 1) & done[stage], stage + 1, stage)
        return stage.astype(jnp.int32)

    def _rewards(self, inner: State, stage: jax.Array, success: jax.Array) -> jax.Array:
        """float32[N]: the subtask rewards of docs/design.md#environments-and-their-contract."""
        n = jnp.arange(self.num_stages)
        progress = jnp.clip(self.spec.per_stage("progress", inner).astype(jnp.float32), 0.0, 1.0)
        rewards = jnp.where(n < stage, 1.0, jnp.where(n == stage, progress, 0.0))
        return jnp.where(success, 1.0, rewards).astype(jnp.float32)

    def _outer(self, inner: State, stage, success, steps, done, truncated=None) -> State:
        rewards = self._rewards(inner, stage, success)
        obs = jnp.asarray(inner.obs, jnp.float32)
        if self.stage_in_obs:
            obs = jnp.concatenate([obs, jax.nn.one_hot(stage, self.num_stages, dtype=jnp.float32)])
        f32 = lambda x: jnp.asarray(x).astype(jnp.float32)
        truncated = jnp.zeros((), bool) if truncated is None else truncated
        inner_keep = {"reward": f32(inner.reward), "done": f32(inner.done),
                      "metrics": dict(inner.metrics), "info": dict(inner.info)}
        return State(
            pipeline_state=inner.pipeline_state,
            obs=obs,
            reward=rewards.sum(),
            done=f32(done),
            metrics={"success": f32(success)},
            info={"stage": stage, "rewards": rewards, "truncation": f32(truncated), "steps": steps,
                  "inner": inner_keep},
        )

    def _inner(self, state: State) -> State:
        """The inner env's State, rebuilt from `state`."""
        keep: dict[str, Any] = state.info["inner"]
        obs = state.obs[: self._inner_obs_size] if self.stage_in_obs else state.obs
        # Fresh dicts: some brax envs update state.metrics in place, which must not touch ours.
        return State(pipeline_state=state.pipeline_state, obs=obs, reward=keep["reward"], done=keep["done"],
                     metrics=dict(keep["metrics"]), info=dict(keep["info"]))
