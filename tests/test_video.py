"""Videos during training (--video-every): the files, their captions, the loggers' env-step axis, refusals before
training, and resuming. One tiny maze run (two members, both filmed every epoch) serves the module."""
from __future__ import annotations

import importlib.machinery
import shutil
import struct
import sys
import types
from pathlib import Path

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccp_jax import outputs, render, video
from ccp_jax.config import ConfigError, make_config
from ccp_jax.envs import make_env
from ccp_jax.policy import load_actors, load_member
from ccp_jax.train import main as train_main
from envs_mjx.maze import Maze

pytestmark = pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # reading MP4 starts ffmpeg
MEMBERS = (1, 0)  # filmed in this order
EPOCHS = (1, 2)  # the tiny preset's


def _fake_wandb(logged: list) -> types.ModuleType:
    """A `wandb` module that records run.log's (step, data); wandb.Video(path) becomes ("video", path)."""
    fake = types.ModuleType("wandb")
    fake.__spec__ = importlib.machinery.ModuleSpec("wandb", None)
    fake.init = lambda **kw: types.SimpleNamespace(log=lambda data, step: logged.append((step, data)),
                                                   finish=lambda: None)
    fake.Video = lambda path: ("video", path)
    return fake


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, list]:
    out = tmp_path_factory.mktemp("video") / "run"
    logged: list = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(sys.modules, "wandb", _fake_wandb(logged))
        train_main(["--preset", "tiny", "--seeds", "2", "--out", str(out), "--no-progress", "--video-every", "1",
                    "--video-members", *map(str, MEMBERS), "--wandb-project", "p"])
    return out, logged


def _env_steps(out: Path) -> list[int]:
    return sorted({r["env_steps"] for r in outputs.read_rows(out / "metrics.jsonl")})


def test_every_epoch_films_each_chosen_member(trained):
    out, _ = trained
    assert sorted(p.name for p in (out / "videos").iterdir()) == [
        f"epoch_{e}_member_{k}.mp4" for e in EPOCHS for k in sorted(MEMBERS)]
    assert '"video_every": 1' in (out / "run.json").read_text()  # what --resume keeps


def test_a_video_is_the_members_episode_acted_by_that_epochs_actors(trained):
    out, _ = trained
    config, actor, params = load_member(out, 1, epoch=EPOCHS[-1])  # the last epoch's checkpoint
    env = make_env(config)
    run = render.episode_program(env, render.acting(config, actor), config.task.max_episode_steps)
    seed = config.members[1][1]
    ep, = render.episodes(run(jax.tree.map(lambda x: x[None], params), jax.random.PRNGKey(seed)[None]))
    frames = iio.imread(out / "videos" / f"epoch_{EPOCHS[-1]}_member_1.mp4")
    assert frames.shape == (ep.steps + 1, 320, 576, 3)  # one frame per state, reset to done
    plain = env.render_frames(ep.states)
    # Below the caption (the maze leaves its top 48 rows for one), the video is the episode's drawing up to MP4's loss.
    assert np.abs(frames[:, 48:].astype(int) - plain[:, 48:]).mean() < 3
    assert np.any(frames[0] != frames[-1])


def test_the_caption_draws_the_stage_and_its_eta_on_each_frame():
    env = Maze(rooms=2, episode_length=10)
    states = [env.state_at(jnp.array([x, 1.5]), jnp.float32(0.0)) for x in (1.0, 6.0)]  # rooms 1 and 2
    stacked = jax.tree.map(lambda *xs: np.stack(xs), *jax.device_get(states))
    ep = render.Episode(stacked, success=False)
    assert list(ep.stage) == [0, 1] and ep.steps == 1
    lines = render.stage_lines(ep, ["0.10", "1.00"], 2)
    assert lines == ["step 0  stage 1/2  η 0.10", "step 1  stage 2/2  η 1.00"]
    plain = env.render_frames(stacked)
    assert np.any(plain[0] != plain[1])  # the robot moved, and changed colour with its stage
    captioned = render.caption(plain, "csac η=0.1 seed 0  member 0  epoch 3", lines)
    changed = np.flatnonzero((captioned != plain).any(axis=(0, 2, 3)))
    assert changed.min() == 0 and changed.max() < 48  # only the band over the maze's empty top margin
    same = render.caption(np.repeat(plain[:1], 2, axis=0), "header", lines)
    assert np.any(same[0] != same[1])  # the same picture, captioned with another stage and η
    with pytest.raises(ValueError, match="1 caption lines for 2 frames"):
        render.caption(plain, "header", lines[:1])


def _events(folder: Path) -> list:
    """Every `Event` in the event files in `folder`, file by file (raw TFRecord read)."""
    from tensorboardX.proto import event_pb2

    found = []
    for path in sorted(folder.glob("events.out.tfevents.*")):
        data, i = path.read_bytes(), 0
        while i < len(data):
            (n,) = struct.unpack("<Q", data[i:i + 8])  # record: length, crc, payload, crc
            found.append(event_pb2.Event.FromString(data[i + 12:i + 12 + n]))
            i += 12 + n + 4
    return found


def _video_events(folder: Path) -> list[tuple[int, bytes]]:
    """(step, encoded image) of every image summary tagged `video` in the event files in `folder`."""
    return [(e.step, v.image.encoded_image_string) for e in _events(folder) for v in e.summary.value
            if v.tag == "video"]


def test_tensorboard_gets_each_video_at_its_epochs_env_steps(trained):
    out, _ = trained
    for member in MEMBERS:
        events = _video_events(out / "tb" / f"member_{member}")
        assert [step for step, _ in events] == _env_steps(out)
        for epoch, (_, gif) in zip(EPOCHS, events):
            frames = iio.imread(gif, extension=".gif")
            assert len(frames) == len(iio.imread(out / "videos" / f"epoch_{epoch}_member_{member}.mp4"))


def test_wandb_gets_metrics_and_videos_at_env_steps(trained):
    out, logged = trained
    steps = _env_steps(out)
    assert [step for step, data in logged if "member_0/success_rate" in data] == steps
    videos = [(step, key, value) for step, data in logged for key, value in data.items() if key.endswith("/video")]
    assert videos == [(step, f"member_{k}/video", ("video", str(out / "videos" / f"epoch_{e}_member_{k}.mp4")))
                      for e, step in zip(EPOCHS, steps) for k in MEMBERS]


def test_videos_compile_their_episode_program_once_and_give_sinks_the_env_steps(trained, tmp_path):
    out, _ = trained
    config = outputs.read_config(out)
    actor, actors = load_actors(out, config)
    videos = video.Videos(config, make_env(config), actor, tmp_path, every=2, members=(0,))
    assert [videos.due(epoch) for epoch in (1, 2, 3, 4)] == [False, True, False, True]
    got = []
    sink = types.SimpleNamespace(video=lambda member, path, frames, fps, steps: got.append((member, path, len(frames),
                                                                                            steps)))
    rows = [{"env_steps": 1234 * epoch, "eta_used": [0.25, 1.0]} for epoch in (1, 2)]
    for epoch in (2, 4):
        videos.record(epoch, jax.device_get(actors), rows, sink)
    assert videos._run._cache_size() == 1  # the second video reused the first one's program
    assert [(m, p, s) for m, p, _, s in got] == [(0, video.video_path(tmp_path, e, 0), 1234) for e in (2, 4)]
    assert got[0][2] == len(iio.imread(got[0][1]))


def test_resume_keeps_the_video_options_and_films_only_the_epochs_it_trains(trained, tmp_path):
    out, _ = trained
    run = shutil.copytree(out, tmp_path / "run")
    (run / "videos" / "epoch_7_member_0.mp4").write_bytes(b"")  # from a longer try, after its last checkpoint
    kept = {p.name: p.stat().st_mtime_ns for p in (run / "videos").iterdir() if not p.name.startswith("epoch_7")}
    train_main(["--resume", str(run), "--total-steps", "600", "--no-progress"])  # one more epoch
    assert sorted(p.name for p in (run / "videos").iterdir()) == [
        f"epoch_{e}_member_{k}.mp4" for e in (*EPOCHS, 3) for k in sorted(MEMBERS)]
    assert {name: (run / "videos" / name).stat().st_mtime_ns for name in kept} == kept  # not filmed again
    # TensorBoard is told the run restarted after epoch 2, so it hides anything logged later before the resume.
    restarts = [e.step for e in _events(run / "tb" / "member_0") if e.session_log.status == e.session_log.START]
    assert restarts == [2 * 200 + 1]
    assert [step for step, _ in _video_events(run / "tb" / "member_0")] == [200, 400, 600]


def test_an_env_that_cannot_be_drawn_is_refused_before_training(tmp_path):
    out = tmp_path / "user"
    with pytest.raises(ConfigError, match=r"^video_every: env 'user_env_module:make' \(StageWrapper\) cannot be drawn"
                                          r" .*give it a method render_frames\(states\)"):
        train_main(["--env", "user_env_module:make", "--preset", "tiny", "--video-every", "2", "--out", str(out),
                    "--no-progress"])
    assert not any((out / name).exists() for name in ("config.json", "metrics.jsonl", "checkpoints", "tb"))


def test_a_user_env_is_drawn_through_its_render_hook():
    from user_env_module import make_drawn  # tests/ is on sys.path (conftest)

    env = make_drawn()
    forward = jax.jit(lambda obs, stage: jnp.ones(obs.shape[:-1] + (1,)))
    ep, = render.rollout(env, forward, jax.random.PRNGKey(0), n=1, max_steps=60)
    assert ep.success and list(np.unique(ep.stage)) == [0, 1]  # 0.25 per step: through both stages
    frames = render.frames_of(render.renderer(env, "user_env_module:make_drawn"), ep, "user_env_module:make_drawn")
    assert frames.shape == (ep.steps + 1, 240, 320, 3) and np.any(frames[0] != frames[-1])
    with pytest.raises(render.RenderError, match=r"render_frames returned uint8\[2, 240, 320, 3\], expected "
                                                 r"uint8\[\d+, H, W, 3\]"):
        render.frames_of(lambda states: frames[:2], ep, "user_env_module:make_drawn")


@pytest.mark.parametrize("argv, message", [
    (["--video-every", "1", "--video-members", "2"], r"^video_members: the grid has members 0\.\.1, got 2"),
    (["--video-every", "1", "--video-members", "1", "1"], r"^video_members: members must be distinct"),
    (["--video-every", "-1"], r"^video_every: must be an integer >= 0"),
])
def test_bad_video_options_are_refused_before_the_run_folder_exists(tmp_path, argv, message):
    out = tmp_path / "x"
    with pytest.raises(ConfigError, match=message):
        train_main(["--preset", "tiny", "--seeds", "2", "--out", str(out), "--no-progress", *argv])
    assert not out.exists()


def test_tp_runs_are_refused_videos():
    config = make_config("tiny", algo="tp", primitives="elsewhere")
    with pytest.raises(ConfigError, match="^video_every: videos act with SAC-family actors"):
        video.check_options(config, 1, (0,))
    video.check_options(config, 0, (0,))  # no videos: nothing to refuse
