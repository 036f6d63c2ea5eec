"""Metric sinks for the host loop: TensorBoard (one event folder per grid member) and,
optionally, Weights & Biases.

    loggers = make_loggers(out, config, tensorboard=True, wandb_project=None)
    loggers.write(outputs.metric_rows(...))   # once per epoch
    loggers.close()

Every sink takes the metrics.jsonl rows of one epoch (one dict per grid member) and logs
their numbers against `env_steps`; a per-agent list `name` becomes tags `name/agent_n`.
Videos made during training (`ccp_jax.video`) go to `video`, at the same env-step axis.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Optional, Protocol, Sequence

import imageio.v3 as iio
import numpy as np

from ccp_jax.config import Config

# Row fields that identify the member or the step rather than measure anything.
ID_FIELDS = ("member", "seed", "eta", "algo", "epoch", "env_steps")


class Sink(Protocol):
    def write(self, rows: Sequence[dict]) -> None: ...

    def video(self, member: int, path: Path, frames: np.ndarray, fps: float, env_steps: int) -> None:
        """Member `member`'s video at `env_steps`: the file written (`path`) and its frames uint8[T, H, W, 3]."""

    def resume(self, env_steps: int) -> None:
        """A resumed run trains again after `env_steps`: what was logged later is superseded."""

    def close(self) -> None: ...


def scalars(row: dict) -> dict[str, float]:
    """The row's metrics as flat tags: numbers as `name`, per-agent lists as `name/agent_n`.

    Undefined entries (None, e.g. η* of the last agent) are left out.
    """
    flat = {}
    for name, value in row.items():
        if name in ID_FIELDS:
            continue
        if isinstance(value, list):
            flat.update({f"{name}/agent_{n}": float(v) for n, v in enumerate(value) if v is not None})
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            flat[name] = float(value)
    return flat


class TensorBoardLogger:
    """One tensorboardX writer per grid member, writing to OUT/tb/member_K (step = env_steps).

    The writers open at the first write, so a resumed run can still say where it restarts (`resume`), and a
    run refused before its first epoch leaves no event file.
    """

    def __init__(self, out: Path, config: Config):
        import tensorboardX  # imported here: only runs that log need it (and a missing one fails before training)

        self._summary_writer = tensorboardX.SummaryWriter
        self.out, self.config = Path(out), config
        self.purge_step: Optional[int] = None
        self._writers: Optional[list] = None

    def resume(self, env_steps: int) -> None:
        """The resumed run trains again after `env_steps` (its checkpoint's): TensorBoard hides what the stopped
        run logged from there on (tensorboardX's purge_step), so the epochs trained again are not drawn twice."""
        self.purge_step = env_steps + 1

    @property
    def writers(self) -> list:
        if self._writers is None:
            eta, seed = self.config.grid_arrays()
            self._writers = [self._summary_writer(logdir=str(self.out / "tb" / f"member_{k}"),
                                                  purge_step=self.purge_step) for k in range(self.config.grid_size)]
            for k, writer in enumerate(self._writers):
                writer.add_text("member", f"algo {self.config.algo}, env {self.config.task.env}, "
                                          f"eta {eta[k].tolist()}, seed {seed[k]}")
        return self._writers

    def write(self, rows: Sequence[dict]) -> None:
        for row in rows:
            writer = self.writers[row["member"]]
            for tag, value in scalars(row).items():
                writer.add_scalar(tag, value, global_step=row["env_steps"])
        for writer in self.writers:
            writer.flush()  # once per epoch, so a crashed run keeps its curves

    def video(self, member: int, path: Path, frames: np.ndarray, fps: float, env_steps: int) -> None:
        """The frames as an animated GIF under the tag `video` (TensorBoard's images tab plays it)."""
        from tensorboardX.summary import Summary

        # What tensorboardX's add_video writes, encoded here: add_video needs moviepy, which ccp-jax does not.
        gif = iio.imwrite("<bytes>", frames, extension=".gif", duration=1000 / fps, loop=0)
        t, height, width, channels = frames.shape
        image = Summary.Image(height=height, width=width, colorspace=channels, encoded_image_string=gif)
        writer = self.writers[member]
        writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag="video", image=image)]), env_steps)
        writer.flush()

    def close(self) -> None:
        for writer in self._writers or ():
            writer.close()


class WandbLogger:
    """One W&B run for the whole grid; member K's tags are logged as `member_K/tag`, step = env_steps (the
    axis TensorBoard's curves use; every member takes the same steps per epoch)."""

    def __init__(self, out: Path, config: Config, project: str):
        import wandb

        self.wandb = wandb
        self.run = wandb.init(project=project, name=Path(out).name, dir=str(out), config=config.to_dict())

    def write(self, rows: Sequence[dict]) -> None:
        if not rows:
            return
        # W&B wants one log call per step with a monotonic step: the epoch's env steps, shared by all members.
        data = {}
        for row in rows:
            tags = {**scalars(row), "epoch": row["epoch"]}
            data.update({f"member_{row['member']}/{tag}": value for tag, value in tags.items()})
        self.run.log(data, step=rows[0]["env_steps"])

    def video(self, member: int, path: Path, frames: np.ndarray, fps: float, env_steps: int) -> None:
        """The video file as `member_K/video`, at the step of the epoch's metrics."""
        self.run.log({f"member_{member}/video": self.wandb.Video(str(path))}, step=env_steps)

    def resume(self, env_steps: int) -> None:
        pass  # a resumed run is a new W&B run: nothing of it to supersede

    def close(self) -> None:
        self.run.finish()


class Loggers:
    """Forwards every call to each of its sinks."""

    def __init__(self, sinks: Sequence[Sink]):
        self.sinks = list(sinks)

    def write(self, rows: Sequence[dict]) -> None:
        for sink in self.sinks:
            sink.write(rows)

    def video(self, member: int, path: Path, frames: np.ndarray, fps: float, env_steps: int) -> None:
        for sink in self.sinks:
            sink.video(member, path, frames, fps, env_steps)

    def resume(self, env_steps: int) -> None:
        for sink in self.sinks:
            sink.resume(env_steps)

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()


def make_loggers(out: Path, config: Config, tensorboard: bool = True, wandb_project: Optional[str] = None) -> Loggers:
    """The sinks asked for (possibly none). W&B is used only when `wandb_project` is given;
    asking for it without the `wandb` package raises ImportError before anything is trained."""
    if wandb_project is not None and importlib.util.find_spec("wandb") is None:
        raise ImportError("wandb_project was given but wandb is not installed: pip install wandb")
    sinks: list[Sink] = []
    if tensorboard:
        sinks.append(TensorBoardLogger(out, config))
    if wandb_project is not None:
        sinks.append(WandbLogger(out, config, wandb_project))
    return Loggers(sinks)
