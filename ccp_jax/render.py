"""Videos of a trained grid member's deterministic episodes.

    python -m ccp_jax.render RUN_DIR --member K [--episodes 2] [--out FILE.mp4|.gif] [--seed S]

Maze: top-down matplotlib frames (walls, goal line, robot, its laser rays and path).
Peg in hole: MuJoCo frames from `envs_mjx.peg_in_hole.render_frames`. MP4 needs the
`imageio-ffmpeg` package; without it the video is written as a GIF instead.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":  # the CLI: MJX's CPU flag and quiet import, before the imports below load brax and MJX
    envs_mjx.configure_cpu()

import argparse
import dataclasses
import functools
import importlib.util
import sys
import warnings
from pathlib import Path
from typing import Callable, Optional, Sequence

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from ccp_jax import outputs
from ccp_jax.envs import make_env
from ccp_jax.plot import group_label
from ccp_jax.policy import load_policy
from envs_mjx.maze import Maze


class RenderError(RuntimeError):
    """The run's env has no renderer here, or the output cannot be written."""


@dataclasses.dataclass
class Episode:
    """One episode from reset to its done step inclusive (T = steps + 1 states).

    obs float32[T, obs_size]; stage int32[T]; pose float32[T, P] (the pipeline state's
    qpos: maze (x, y, heading), MJX the model's qpos); reward float32[T] (0 at reset);
    success bool (the last state succeeded).
    """

    obs: np.ndarray
    stage: np.ndarray
    pose: np.ndarray
    reward: np.ndarray
    success: bool

    @property
    def steps(self) -> int:
        return len(self.stage) - 1


def _pose(state: State) -> jax.Array:
    qpos = state.pipeline_state.qpos
    return qpos() if callable(qpos) else qpos  # the maze's RobotPose.qpos is a method, mjx.Data's a field


def rollout(env: Env, policy: Callable, key: jax.Array, episodes: int, max_steps: int) -> list[Episode]:
    """`episodes` deterministic episodes of `policy(obs, stage) -> action`, run in parallel.

    One jitted vmapped `lax.scan` of `max_steps` steps; an episode that is done stays
    frozen and is cut at its done step (or at `max_steps`).
    """
    def one(k: jax.Array):
        def step(state: State, _):
            nxt = env.step(state, policy(state.obs, state.info["stage"]))
            state = jax.tree.map(lambda a, b: jnp.where(state.done > 0, a, b), state, nxt)
            return state, record(state, state.reward)

        def record(state: State, reward: jax.Array):
            return state.obs, state.info["stage"], _pose(state), reward, state.done, state.metrics["success"]

        first = env.reset(k)
        _, trace = jax.lax.scan(step, first, None, length=max_steps)
        start = record(first, jnp.zeros_like(first.reward))  # no step taken yet: no reward
        return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), start, trace)

    obs, stage, pose, reward, done, success = jax.device_get(jax.jit(jax.vmap(one))(jax.random.split(key, episodes)))
    out = []
    for e in range(episodes):
        ends = np.flatnonzero(done[e] > 0)
        t = int(ends[0]) if len(ends) else max_steps
        out.append(Episode(obs[e, :t + 1], stage[e, :t + 1], pose[e, :t + 1], reward[e, :t + 1],
                           bool(success[e, t] > 0)))
    return out


def maze_frames(env: Maze, episode: Episode, title: str = "", px_per_m: int = 48) -> np.ndarray:
    """Top-down frames of a maze episode, uint8[T, H, W, 3].

    H = 5·px_per_m + 80 and W = 5N·px_per_m + 96 (multiples of 16 at the default
    scale, as video encoders want). Rays are the observation's laser beams
    (obs[:n_beams] · beam range, beam i at heading + 2πi/n_beams).
    """
    g = env.geometry
    width, height = int(g.width * px_per_m) + 96, int(g.room_size * px_per_m) + 80
    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    # Fixed axes box (no auto layout), so nothing shifts between frames when the title changes.
    ax = fig.add_axes((48 / width, 32 / height, g.width * px_per_m / width, g.room_size * px_per_m / height))
    ax.set_xlim(0, g.width)
    ax.set_ylim(0, g.room_size)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    ax.add_collection(LineCollection(env.walls.reshape(-1, 2, 2), colors="0.2", linewidths=2.5))
    ax.axvline(g.goal_x, color="tab:green", linestyle="--", linewidth=1.5)
    rays = ax.add_collection(LineCollection([], colors="tab:red", linewidths=0.6, alpha=0.6))
    path, = ax.plot([], [], color="tab:blue", linewidth=1, alpha=0.6)
    robot = ax.add_patch(Circle((0, 0), g.robot_radius, edgecolor="black", linewidth=0.8))
    heading, = ax.plot([], [], color="black", linewidth=1.5)
    title_text = fig.suptitle("", fontsize=9, y=1 - 8 / height, va="top")
    stage_colours = [f"C{i}" for i in range(10)]

    offsets = 2 * np.pi * np.arange(g.n_beams) / g.n_beams
    frames = np.empty((episode.steps + 1, height, width, 3), np.uint8)
    for t in range(episode.steps + 1):
        x, y, theta = episode.pose[t, :3]
        ends = episode.obs[t, :g.n_beams, None] * g.beam_range * np.stack(
            [np.cos(theta + offsets), np.sin(theta + offsets)], axis=-1)
        rays.set_segments(np.stack([np.broadcast_to((x, y), ends.shape), (x, y) + ends], axis=1))
        path.set_data(episode.pose[:t + 1, 0], episode.pose[:t + 1, 1])
        robot.center = (x, y)
        robot.set_facecolor(stage_colours[episode.stage[t] % 10])  # colour = acting stage's agent
        heading.set_data([x, x + 2 * g.robot_radius * np.cos(theta)], [y, y + 2 * g.robot_radius * np.sin(theta)])
        done = " — success" if t == episode.steps and episode.success else ""
        title_text.set_text(f"{title}step {t}  stage {episode.stage[t] + 1}/{g.rooms}{done}")
        canvas.draw()
        frames[t] = np.asarray(canvas.buffer_rgba())[..., :3]
    return frames


def frame_renderer(env: Env) -> Callable[[Episode, str], np.ndarray]:
    """`draw(episode, title) -> uint8[T, H, W, 3]` for `env`; RenderError (before any rollout) if none."""
    if isinstance(env, Maze):
        return functools.partial(maze_frames, env)
    peg = sys.modules.get("envs_mjx.peg_in_hole")  # imported by make_env when the run is a peg run
    if peg is not None and isinstance(env, peg.PegInHole):
        if not hasattr(peg, "render_frames"):
            raise RenderError("this envs_mjx.peg_in_hole has no render_frames; peg videos need it")
        return lambda episode, title="": peg.render_frames(env, episode.pose)
    raise RenderError(f"no renderer for {type(env).__name__}; render supports the maze and peg-in-hole envs")


def has_ffmpeg() -> bool:
    return importlib.util.find_spec("imageio_ffmpeg") is not None


def write_video(path: Path, frames: np.ndarray, fps: float) -> Path:
    """Writes uint8[T, H, W, 3] frames as .mp4 or .gif; an .mp4 without imageio-ffmpeg becomes
    a .gif next to it (with a note on stderr). Returns the path written."""
    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise RenderError(f"--out must end in .mp4 or .gif, got {path.name}")
    if suffix == ".mp4" and not has_ffmpeg():
        path = path.with_suffix(".gif")
        print(f"note: MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg); writing {path} instead", file=sys.stderr)
        suffix = ".gif"
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".gif":
        iio.imwrite(path, frames, extension=".gif", duration=1000 / fps, loop=0)
        return path
    with warnings.catch_warnings():
        # ffmpeg is started by fork + exec at once, which JAX's fork warning does not apply to.
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        iio.imwrite(path, frames, extension=".mp4", fps=fps, codec="libx264", quality=7, macro_block_size=16)
    return path


def render(run_dir: Path, member: int = 0, episodes: int = 2, out: Optional[Path] = None, seed: int = 0,
           fps: float = 10.0, epoch: Optional[int] = None) -> tuple[Path, list[Episode]]:
    """Renders `episodes` deterministic episodes of grid member `member` into one video.

    Default output: RUN_DIR/member_K.mp4 (.gif without imageio-ffmpeg). Each episode ends
    with its last frame held for half a second. Returns (video path, episodes).
    """
    config = outputs.read_config(run_dir)
    env = make_env(config)
    draw = frame_renderer(env)
    policy = load_policy(run_dir, member, epoch=epoch)
    eps = rollout(env, policy, jax.random.PRNGKey(seed), episodes, config.task.max_episode_steps)
    label = f"{group_label(('', config.algo, config.members[member][0]))}  member {member}"
    hold = max(1, int(fps / 2))
    clips = []
    for e, ep in enumerate(eps):
        frames = draw(ep, f"{label}  episode {e + 1}/{episodes}  ")
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
