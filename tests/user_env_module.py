"""A user's own env, as `--env user_env_module:make` would load it (tests/ is on sys.path).

`Slider` is a bare `brax.envs.base.Env` that knows nothing of stages: a point
x in [0, 2] moved by 0.25 * a per step. `make()` turns it into a two-stage task
with `StageWrapper` in a few lines: cross [0, 1], then [1, 2].
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from envs_mjx.stage_wrapper import StageSpec, StageWrapper


class Slider(Env):
    """x starts in [0, 0.2]; obs float32[1] = [x]; reward 0; never done by itself."""

    speed = 0.25

    @property
    def observation_size(self) -> int:
        return 1

    @property
    def action_size(self) -> int:
        return 1

    @property
    def backend(self) -> str:
        return "jax"

    def reset(self, rng: jax.Array) -> State:
        x = jax.random.uniform(rng, (), jnp.float32, 0.0, 0.2)
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=x, obs=x[None], reward=zero, done=zero)

    def step(self, state: State, action: jax.Array) -> State:
        x = jnp.clip(state.pipeline_state + self.speed * action[0], 0.0, 2.0)
        return state.replace(pipeline_state=x, obs=x[None])


SPEC = StageSpec(
    num_stages=2,
    progress=(lambda s: s.obs[0], lambda s: s.obs[0] - 1.0),
    completed=(lambda s: s.obs[0] >= 1.0, lambda s: s.obs[0] >= 1.9),
)


def make() -> StageWrapper:
    """The factory `--env user_env_module:make` calls."""
    return StageWrapper(Slider(), SPEC, episode_length=50)


class DrawnSlider(Slider):
    """`Slider` with the contract's render hook, as docs/own-task.md#videos shows it."""

    def render_frames(self, states: State) -> np.ndarray:
        frames = []
        for x in states.pipeline_state:  # the point's position per step
            fig = Figure(figsize=(3.2, 2.4), dpi=100)  # 320 x 240
            canvas = FigureCanvasAgg(fig)
            ax = fig.add_subplot()
            ax.set_xlim(0, 2)
            ax.set_ylim(-1, 1)
            ax.plot([x], [0], "o")
            canvas.draw()
            frames.append(np.asarray(canvas.buffer_rgba())[..., :3])
        return np.stack(frames)


def make_drawn() -> StageWrapper:
    """The factory of a user env that can be drawn (`--env user_env_module:make_drawn`)."""
    return StageWrapper(DrawnSlider(), SPEC, episode_length=50)


class _StageSkipping(StageWrapper):
    """Reports stage 1 from the first step on while its rewards still say stage 0: breaks the contract."""

    def step(self, state: State, action: jax.Array) -> State:
        state = super().step(state, action)
        return state.replace(info={**state.info, "stage": jnp.ones_like(state.info["stage"]) * 5})


def make_broken() -> StageWrapper:
    """A factory whose env the CLI must refuse before compiling anything."""
    return _StageSkipping(Slider(), SPEC, episode_length=50)


class _LateNaN(StageWrapper):
    """Its observations turn NaN from the 70th step of an episode on: a fault only a whole episode shows."""

    def step(self, state: State, action: jax.Array) -> State:
        state = super().step(state, action)
        return state.replace(obs=jnp.where(state.info["steps"] >= 70, jnp.nan, state.obs))


def make_late_nan() -> StageWrapper:
    """Breaks the contract at step 70 of its 100-step episodes."""
    return _LateNaN(Slider(), SPEC, episode_length=100)


def make_raising() -> StageWrapper:
    """A factory whose own code fails."""
    raise RuntimeError("no licence for the simulator")


not_a_factory = 42
