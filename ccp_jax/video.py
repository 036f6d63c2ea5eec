"""Videos during training: every K epochs, one deterministic evaluation episode of chosen grid members.

    videos = Videos(config, env, actor, out, every=5, members=(0, 2))   # refuses an env it cannot draw
    if videos.due(epoch):
        videos.record(epoch, actors, rows, sinks)                     # actors: host copies, leaves [G, N, ...]

Each video is one episode from a fixed start state (the member's seed), acted by the member's current
actors, drawn by the env's render hook (`ccp_jax.render`) and captioned with the epoch, the member and, on
every frame, the acting stage and the η its agent trained with this epoch (the metrics row's `eta_used`). It is
written to OUT/videos/epoch_<N>_member_<K>.mp4 (.gif without imageio-ffmpeg) and given to the loggers at
the epoch's env steps. The episode program is compiled at the first video and reused for the later ones.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import jax
import numpy as np
from brax.envs.base import Env

from ccp_jax import render
from ccp_jax.config import Config, ConfigError
from ccp_jax.loggers import Loggers
from ccp_jax.networks import Actor
from ccp_jax.plot import group_label

VIDEO_DIR = "videos"
FPS = 20.0


def check_options(config: Config, every: int, members: Sequence[int]) -> None:
    """Refuses video options that cannot work, naming the field, before anything is built or compiled."""
    if isinstance(every, bool) or not isinstance(every, int) or every < 0:
        raise ConfigError("video_every", f"must be an integer >= 0 (0: no videos), got {every!r}")
    if not members:
        raise ConfigError("video_members", "give at least one grid member")
    for k in members:
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k < config.grid_size:
            raise ConfigError("video_members", f"the grid has members 0..{config.grid_size - 1}, got {k!r}")
    if len(set(members)) != len(members):
        raise ConfigError("video_members", f"members must be distinct, got {tuple(members)}")
    if every and config.algo == "tp":
        raise ConfigError("video_every", "videos act with SAC-family actors (csac, naive, sac); a TP run's "
                                         "transition policies are not supported")


def check_renderable(config: Config, env: Env) -> None:
    """Refuses, naming the env and how to give it a renderer, an env that cannot be drawn here: one without a
    render hook, or whose hook fails on its reset state (e.g. MuJoCo without an OpenGL backend)."""
    try:
        render.check_draws(env, config.task.env, jax.random.PRNGKey(0))
    except render.RenderError as err:
        raise ConfigError("video_every", f"{err}; or leave --video-every at 0") from None


def video_path(out: Path, epoch: int, member: int) -> Path:
    return Path(out) / VIDEO_DIR / f"epoch_{epoch}_member_{member}.mp4"


def forget_after(out: Path, epoch: int) -> list[Path]:
    """Deletes the videos of epochs after `epoch` (a resumed run trains those again); returns them."""
    gone = []
    for path in sorted((Path(out) / VIDEO_DIR).glob("epoch_*_member_*")):
        try:
            later = int(path.name.split("_")[1]) > epoch
        except ValueError:  # not a name this module writes
            continue
        if later:
            path.unlink()
            gone.append(path)
    return gone


class Videos:
    """Videos of `members` every `every` (>= 1) epochs of a run in `out` (see the module docstring).

    Refuses (ConfigError on video_every) an env that cannot be drawn, drawing its reset state once."""

    def __init__(self, config: Config, env: Env, actor: Actor, out: Path, every: int, members: Sequence[int]):
        check_options(config, every, members)
        if not every:
            raise ValueError("Videos needs every >= 1 (0: make no Videos)")
        self.config, self.out, self.every, self.members = config, Path(out), every, tuple(members)
        check_renderable(config, env)
        self.draw = render.renderer(env, config.task.env)
        self._run = render.episode_program(env, render.acting(config, actor), config.task.max_episode_steps)
        _, seeds = config.grid_arrays()
        # One fixed start per member, so its videos show the same episode start as training goes on.
        self._keys = jax.numpy.stack([jax.random.PRNGKey(int(seeds[k])) for k in self.members])

    def due(self, epoch: int) -> bool:
        """Whether epoch `epoch` (1-based) gets videos."""
        return epoch % self.every == 0

    def record(self, epoch: int, actors: Any, rows: Sequence[dict], sinks: Loggers) -> list[Path]:
        """Videos of epoch `epoch` (1-based): `actors` the grid's actor parameters (host copies, leaves
        [G, N, ...]), `rows` the epoch's metrics rows (one per member). Returns the files written."""
        idx = np.asarray(self.members)
        eps = render.episodes(self._run(jax.tree.map(lambda x: np.asarray(x)[idx], actors), self._keys))
        paths = []
        for member, ep in zip(self.members, eps):
            row = rows[member]
            frames = render.caption(render.frames_of(self.draw, ep, self.config.task.env),
                                    self._header(member, epoch, row["env_steps"]),
                                    render.stage_lines(ep, [f"{x:.2f}" for x in row["eta_used"]],
                                                       self.config.num_stages))
            path = render.write_video(video_path(self.out, epoch, member), frames, FPS)
            sinks.video(member, path, frames, FPS, row["env_steps"])
            paths.append(path)
        return paths

    def _header(self, member: int, epoch: int, env_steps: int) -> str:
        eta, seed = self.config.members[member]
        label = group_label(("", self.config.algo, eta))
        return f"{label} seed {seed}  member {member}  epoch {epoch}  {env_steps:,} steps"
