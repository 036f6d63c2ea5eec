"""Videos of a grid member's deterministic episodes, captioned with the acting stage and its η.

    python -m ccp_jax.render RUN_DIR --member K [--episodes 2] [--out FILE.mp4|.gif] [--seed S]

Every env is drawn by its own render hook, `env.render_frames(states) -> uint8[T, H, W, 3]`
(docs/design.md#environments-and-their-contract; `envs_mjx.frames`): the maze top-down with matplotlib,
peg in hole and pusher through MuJoCo's offscreen renderer (which needs an OpenGL backend: MUJOCO_GL=egl
or osmesa), a user's env through its own method. An env without one is refused before anything is rolled
out (`renderer`). The same pieces make the videos during training (`ccp_jax.video`). MP4 needs the
`imageio-ffmpeg` package; without it a video is written as a GIF instead.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":  # the CLI: MJX's CPU flag and quiet import, before the imports below load brax and MJX
    envs_mjx.configure_cpu()

import argparse
import dataclasses
import importlib.util
import os
import sys
import warnings
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from brax.envs.base import Env, State

from ccp_jax import outputs
from ccp_jax.config import Config
from ccp_jax.envs import make_env
from ccp_jax.networks import Actor
from ccp_jax.plot import group_label
from ccp_jax.policy import chain_policy, load_member

Draw = Callable[[State], np.ndarray]  # one episode's stacked states [T, ...] -> uint8[T, H, W, 3]
Act = Callable[[Any, jax.Array, jax.Array], jax.Array]  # (params, obs [O], stage int32[]) -> action [A]


class RenderError(RuntimeError):
    """The run's env cannot be drawn, or the output cannot be written."""


@dataclasses.dataclass
class Episode:
    """One episode from reset to its done step inclusive: `states` is its `State`s stacked (host numpy leaves
    [T, ...], T = steps + 1); success: the last state succeeded."""

    states: State
    success: bool

    @property
    def steps(self) -> int:
        return len(self.stage) - 1

    @property
    def obs(self) -> np.ndarray:
        """float32[T, obs_size]."""
        return np.asarray(self.states.obs)

    @property
    def stage(self) -> np.ndarray:
        """int32[T], 0-based."""
        return np.asarray(self.states.info["stage"])

    @property
    def reward(self) -> np.ndarray:
        """float32[T], the reward of the step into each state (0 at reset)."""
        reward = np.array(self.states.reward, np.float32)
        reward[0] = 0.0
        return reward


def episode_program(env: Env, act: Act, max_steps: int) -> Callable[[Any, jax.Array], State]:
    """jitted run(params, keys uint32[E, 2]) -> `State` with leaves [E, max_steps + 1, ...]: E deterministic
    episodes, episode e with its own actor parameters (leaves [E, ...]) and start key, each frozen from its done
    step on (`episodes` cuts them there). Compiled once per shape, so later calls cost only the rollout."""

    def one(params: Any, key: jax.Array) -> State:
        def step(state: State, _):
            nxt = env.step(state, act(params, state.obs, state.info["stage"]))
            state = jax.tree.map(lambda a, b: jnp.where(state.done > 0, a, b), state, nxt)
            return state, state

        first = env.reset(key)
        _, trace = jax.lax.scan(step, first, None, length=max_steps)
        return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, trace)

    return jax.jit(jax.vmap(one))


def episodes(trace: State) -> list[Episode]:
    """`episode_program`'s output (leaves [E, T_max, ...]), on the host, cut at each episode's first done."""
    trace = jax.device_get(trace)
    done, success = np.asarray(trace.done), np.asarray(trace.metrics["success"])
    out = []
    for e in range(done.shape[0]):
        ends = np.flatnonzero(done[e] > 0)
        t = int(ends[0]) if len(ends) else done.shape[1] - 1
        out.append(Episode(jax.tree.map(lambda x: np.asarray(x[e, :t + 1]), trace), bool(success[e, t] > 0)))
    return out


def acting(config: Config, actor: Actor) -> Act:
    """act(params, obs [O], stage int32[]) -> action [A]: one member's deterministic action (params: its actor
    parameters, leaves [N, ...]) by the agent of the stage (`policy.chain_policy`)."""
    return lambda params, obs, stage: chain_policy(config, actor, params)(obs[None], stage[None])[0]


def rollout(env: Env, policy: Callable, key: jax.Array, n: int, max_steps: int) -> list[Episode]:
    """`n` deterministic episodes of `policy(obs, stage) -> action`, run in parallel (compiled per call)."""
    run = episode_program(env, lambda _, obs, stage: policy(obs, stage), max_steps)
    return episodes(run(jnp.zeros(n), jax.random.split(key, n)))


def renderer(env: Env, name: str) -> Draw:
    """The env's render hook (`envs_mjx.frames`); a RenderError naming env `name` and how to give it one if it
    has none. Nothing is drawn here (`check_draws` draws one frame)."""
    try:
        draw = env.render_frames
    except AttributeError as err:
        # A wrapper's hook (StageWrapper's) says why its inner env cannot be drawn; a plain missing method does not.
        why = f" ({err})" if isinstance(getattr(type(env), "render_frames", None), property) else ""
        raise RenderError(
            f"env {name!r} ({type(env).__name__}) cannot be drawn{why}: give it a method render_frames(states) -> "
            "uint8[T, H, W, 3] that draws one episode's stacked states (docs/own-task.md#videos)") from None
    if not callable(draw):
        raise RenderError(f"env {name!r} ({type(env).__name__}): render_frames is not callable")
    return draw


def frames_of(draw: Draw, episode: Episode, name: str) -> np.ndarray:
    """`draw`'s frames of `episode`, uint8[T, H, W, 3] with T = steps + 1; a RenderError naming env `name` if the
    hook returns anything else."""
    frames = np.asarray(draw(episode.states))
    expected = f"uint8[{episode.steps + 1}, H, W, 3]"
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[0] != episode.steps + 1 or frames.shape[-1] != 3:
        raise RenderError(f"env {name!r}: render_frames returned {frames.dtype}{list(frames.shape)}, "
                          f"expected {expected}")
    return frames


def check_draws(env: Env, name: str, key: jax.Array) -> None:
    """Draws the reset state of `env` once, so a missing hook or OpenGL backend stops a run before it trains."""
    draw = renderer(env, name)
    state = jax.device_get(jax.jit(env.reset)(key))
    try:
        frames_of(draw, Episode(jax.tree.map(lambda x: np.asarray(x)[None], state), False), name)
    except RuntimeError as err:  # MuJoCo without OpenGL: the message says what to set
        raise RenderError(f"env {name!r} cannot be drawn here: {err}") from None


# DejaVu Sans, which matplotlib ships: it has the Greek letters Pillow's own default font lacks (η).
_FONT = str(Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf")


def caption(frames: np.ndarray, header: str, lines: Sequence[str]) -> np.ndarray:
    """`frames` uint8[T, H, W, 3] with a dark band across the top holding `header` and frame t's `lines[t]`."""
    from PIL import Image, ImageDraw, ImageFont  # local: only videos draw text

    t, height, width, _ = frames.shape
    if len(lines) != t:
        raise ValueError(f"{len(lines)} caption lines for {t} frames")
    size = max(11, height // 24)
    font = ImageFont.truetype(_FONT, size)
    band = 2 * size + 12
    out = np.empty_like(frames)
    for i in range(t):
        image = Image.fromarray(frames[i])
        pen = ImageDraw.Draw(image, "RGBA")
        pen.rectangle((0, 0, width, band), fill=(0, 0, 0, 160))
        pen.text((6, 4), header, fill=(255, 255, 255), font=font)
        pen.text((6, 8 + size), lines[i], fill=(255, 255, 255), font=font)
        out[i] = np.asarray(image)
    return out


def stage_lines(episode: Episode, etas: Sequence[str], num_stages: int) -> list[str]:
    """One caption line per frame: the step, the acting stage (1-based, of `num_stages`) and its agent's η
    (`etas`: one text per agent; a single agent acts in every stage)."""
    lines = []
    for t, stage in enumerate(episode.stage):
        eta = etas[0] if len(etas) == 1 else etas[min(int(stage), len(etas) - 1)]
        end = "  success" if t == episode.steps and episode.success else ""
        lines.append(f"step {t}  stage {int(stage) + 1}/{num_stages}  η {eta}{end}")
    return lines


def has_ffmpeg() -> bool:
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def write_video(path: Path, frames: np.ndarray, fps: float) -> Path:
    """Writes uint8[T, H, W, 3] frames as .mp4 or .gif; an .mp4 without imageio-ffmpeg becomes a .gif next to it
    (with a note on stderr). Written under a temporary name and then renamed, so a crash leaves no half video.
    Returns the path written."""
    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise RenderError(f"--out must end in .mp4 or .gif, got {path.name}")
    if suffix == ".mp4" and not has_ffmpeg():
        path = path.with_suffix(".gif")
        print(f"note: MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg); writing {path} instead", file=sys.stderr)
        suffix = ".gif"
    path.parent.mkdir(parents=True, exist_ok=True)
    part = path.with_name(f"{path.stem}.part{suffix}")  # ffmpeg picks its format by the name's ending
    if suffix == ".gif":
        iio.imwrite(part, frames, extension=".gif", duration=1000 / fps, loop=0)
    else:
        with warnings.catch_warnings():
            # ffmpeg is started by fork + exec at once, which JAX's fork warning does not apply to.
            warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
            iio.imwrite(part, frames, extension=".mp4", fps=fps, codec="libx264", quality=7, macro_block_size=16)
    os.replace(part, path)
    return path


def render(run_dir: Path, member: int = 0, n: int = 2, out: Optional[Path] = None, seed: int = 0,
           fps: float = 10.0, epoch: Optional[int] = None) -> tuple[Path, list[Episode]]:
    """Renders `n` deterministic episodes of grid member `member` into one video.

    Default output: RUN_DIR/member_K.mp4 (.gif without imageio-ffmpeg). Each episode ends
    with its last frame held for half a second. Returns (video path, episodes).
    """
    config = outputs.read_config(run_dir)
    if config.algo == "tp":
        raise ValueError("algo: render loads SAC-family actors (csac, naive, sac); a TP run's transition "
                         "policies are not supported")
    env = make_env(config)
    draw = renderer(env, config.task.env)
    config, actor, params = load_member(run_dir, member, epoch)
    run = episode_program(env, acting(config, actor), config.task.max_episode_steps)
    stacked = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), params)
    eps = episodes(run(stacked, jax.random.split(jax.random.PRNGKey(seed), n)))
    eta = config.members[member][0]
    label = f"{group_label(('', config.algo, eta))}  member {member}"
    etas = [x if isinstance(x, str) else f"{x:g}" for x in eta]
    hold = max(1, int(fps / 2))
    clips = []
    for e, ep in enumerate(eps):
        frames = caption(frames_of(draw, ep, config.task.env), f"{label}  episode {e + 1}/{n}",
                         stage_lines(ep, etas, config.num_stages))
        clips.append(np.concatenate([frames, np.repeat(frames[-1:], hold, axis=0)]))
    if len({c.shape[1:] for c in clips}) != 1:
        raise RenderError("episodes rendered at different frame sizes")
    out = Path(run_dir) / f"member_{member}.mp4" if out is None else Path(out)
    return write_video(out, np.concatenate(clips), fps), eps


def main(argv: Optional[Sequence[str]] = None) -> Path:
    envs_mjx.configure_cpu()  # before anything starts JAX
    parser = argparse.ArgumentParser(prog="python -m ccp_jax.render",
                                     description="Video of a trained grid member's deterministic episodes.")
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR")
    parser.add_argument("--member", type=int, default=0, help="grid member (see summary.json)")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--out", type=Path, help="FILE.mp4 or FILE.gif (default RUN_DIR/member_K.mp4)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes' start states")
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--epoch", type=int, help="checkpoint epoch (default: the latest)")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.fps <= 0:
        parser.error("--episodes must be >= 1 and --fps > 0")
    try:
        path, eps = render(args.run_dir, args.member, args.episodes, args.out, args.seed, args.fps, args.epoch)
    except (RenderError, ValueError, FileNotFoundError) as err:
        parser.exit(2, f"error: {err}\n")
    for e, ep in enumerate(eps):
        print(f"episode {e + 1}: {ep.steps} steps, return {ep.reward.sum():.1f}, "
              f"stage reached {int(ep.stage.max()) + 1}, {'success' if ep.success else 'no success'}")
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main()
