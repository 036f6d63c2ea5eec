"""Plots, videos, re-evaluation and metric loggers made from a real (tiny) run folder."""
from __future__ import annotations

import importlib.machinery
import json
import re
import struct
import subprocess
import sys
import types
from pathlib import Path

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccp_jax import evaluate, loggers, outputs, plot, render
from ccp_jax.config import Config, ConfigError
from ccp_jax.train import main as train_main
from envs_mjx.maze import Maze
from toy_env import Line  # tests/ is on sys.path (conftest)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "tiny"
    train_main(["--preset", "tiny", "--seeds", "2", "--out", str(out), "--no-progress"])
    return out


@pytest.fixture(scope="module")
def config(run_dir) -> Config:
    return Config.from_dict(json.loads((run_dir / "config.json").read_text()))


def _decoded_png(path: Path) -> np.ndarray:
    assert path.stat().st_size > 5000
    image = iio.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert len(np.unique(image.reshape(-1, image.shape[-1]), axis=0)) > 10  # something was drawn
    return image


# ----- plots -------------------------------------------------------------------------------------
def test_plot_cli_writes_success_png(run_dir):
    assert plot.main([str(run_dir)]) == run_dir / "success.png"
    _decoded_png(run_dir / "success.png")


def test_plot_per_agent_metric_and_bad_metric(run_dir, tmp_path):
    out = plot.main([str(run_dir), "--metric", "q_loss/1", "--out", str(tmp_path / "q.png")])
    _decoded_png(out)
    with pytest.raises(SystemExit):
        plot.main([str(run_dir), "--metric", "q_loss"])  # per-agent without an agent index
    with pytest.raises(SystemExit):
        plot.main([str(run_dir), "--metric", "no_such_metric"])
    for metric, message in [("q_loss/5", "'q_loss' is per agent; write q_loss/K for agent K (0..1), got 'q_loss/5'"),
                            ("success_rate/1", "'success_rate' is one number per epoch, not per agent"),
                            ("eval_end", "'eval_end' holds ['pocket']; write eval_end/NAME for one of them, got 'eval_end'"),
                            ("eval_end/door", "'eval_end' holds ['pocket']; write eval_end/NAME")]:
        with pytest.raises(ConfigError, match=re.escape(f"metric: {message}")):  # was an IndexError for q_loss/5
            plot.load_curves([run_dir], metric)


def test_env_diagnostic_at_the_evaluations_end_is_a_curve(run_dir):
    rows = sorted(outputs.read_rows(outputs.metrics_file(run_dir)), key=lambda r: (r["member"], r["epoch"]))
    expected = [[r["eval_end"]["pocket"] for r in rows if r["member"] == m] for m in (0, 1)]
    series, = plot.load_curves([run_dir], "eval_end/pocket").values()  # one group: one ratio, two seeds
    assert sorted(values.tolist() for _, values in series) == sorted(expected)
    assert plot.main([str(run_dir), "--metric", "eval_end/pocket"]) == run_dir / "eval_end_pocket.png"


def test_stage_fraction_plot_is_labelled_by_stage_and_spans_fractions(run_dir):
    groups = plot.load_curves([run_dir], "stage_fraction/1")
    ax = plot.curves(groups, "stage_fraction/1").axes[0]
    assert ax.get_ylabel() == "fraction of evaluations reaching stage 2"
    assert ax.get_ylim() == (-0.02, 1.02)
    steps = np.array([10, 20])  # three seeds, mean ± std = 0.67 ± 0.47 at both steps: the band is clipped to [0, 1]
    seeds = {("peg", "naive", (1.0, 1.0)): [(steps, np.ones(2)), (steps, np.ones(2)), (steps, np.zeros(2))]}
    band, = plot.curves(seeds, "stage_fraction/1").axes[0].collections
    np.testing.assert_allclose([band.get_paths()[0].vertices[:, 1].min(), band.get_paths()[0].vertices[:, 1].max()],
                               [2 / 3 - np.sqrt(2) / 3, 1.0])
    assert plot.curves(groups, "q_loss/1").axes[0].get_ylabel() == "q loss/1"


def test_panels_side_by_side_draw_a_variant_in_one_colour():
    steps = np.array([10, 20])
    one = [(steps, np.zeros(2))]
    left = {("maze-2", "sac", (1.0, 1.0)): one, ("maze-2", "csac", (0.1, 1.0)): one}
    right = {("peg", "naive", (1.0, 1.0)): one, ("peg", "sac", (1.0, 1.0)): one}  # sac second here, first left
    colors = plot.line_colors([left, right])
    assert colors == {"csac η=0.1": "C0", "sac": "C1", "naive": "C2"}
    fig = plot.new_figure()
    drawn = [plot.curves(groups, ax=fig.add_subplot(1, 2, i + 1), colors=colors).axes[i] for i, groups in
             enumerate([left, right])]
    by_label = [{line.get_label().split(" (n=")[0]: line.get_color() for line in ax.get_lines()} for ax in drawn]
    assert by_label[0]["sac"] == by_label[1]["sac"] == "C1"
    assert by_label[1]["naive"] == "C2" and by_label[0]["csac η=0.1"] == "C0"
    many = {("maze-2", "csac", (eta / 100, 1.0)): one for eta in range(1, 13)}  # 12 variants: beyond the cycle
    assert len(set(plot.line_colors([many]).values())) == 12


def test_plot_labels_keep_runs_of_one_algo_apart(run_dir, tmp_path, monkeypatch):
    drawn = {}
    real = plot.curves
    monkeypatch.setattr(plot, "curves", lambda groups, *a, **k: drawn.update(groups) or real(groups, *a, **k))
    plot.main([str(run_dir), str(run_dir), "--labels", "csac (a)", "csac (b)", "--out", str(tmp_path / "ab.png")])
    assert sorted(g[1] for g in drawn) == ["csac (a)", "csac (b)"]
    assert plot.group_label(next(iter(drawn))).endswith("η=0.1")
    with pytest.raises(SystemExit):
        plot.main([str(run_dir), "--labels", "a", "b"])


def test_plot_labels_pool_the_seeds_of_folders_with_one_label(run_dir, tmp_path, monkeypatch):
    import shutil

    halves = []
    for seed in (0, 1):  # the tiny run's two seeds, one per folder
        half = tmp_path / f"seed{seed}"
        shutil.copytree(run_dir, half)
        rows = [r for r in (half / "metrics.jsonl").read_text().splitlines() if json.loads(r)["seed"] == seed]
        (half / "metrics.jsonl").write_text("\n".join(rows) + "\n")
        halves.append(str(half))
    drawn = {}
    real = plot.curves
    monkeypatch.setattr(plot, "curves", lambda groups, *a, **k: drawn.update(groups) or real(groups, *a, **k))
    plot.main(halves + [str(run_dir), "--labels", "pooled", "pooled", "whole", "--out", str(tmp_path / "p.png")])
    assert {g[1]: len(series) for g, series in drawn.items()} == {"pooled": 2, "whole": 2}


def test_a_label_over_several_ratios_names_each(run_dir, tmp_path, monkeypatch):
    import shutil

    mixed = tmp_path / "mixed"
    shutil.copytree(run_dir, mixed)
    rows = [json.loads(r) for r in (mixed / "metrics.jsonl").read_text().splitlines()]
    for r in rows:  # seed 1 becomes a second ratio's member
        r["eta"] = [0.5, 1.0] if r["seed"] == 1 else r["eta"]
    (mixed / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    drawn = {}
    real = plot.curves
    monkeypatch.setattr(plot, "curves", lambda groups, *a, **k: drawn.update(groups) or real(groups, *a, **k))
    plot.main([str(mixed), str(run_dir), "--labels", "variant", "other", "--out", str(tmp_path / "m.png")])
    assert {g[1]: len(series) for g, series in drawn.items()} == {
        "variant, csac η=0.1": 1, "variant, csac η=0.5": 1, "other": 2}


def test_load_curves_groups_members_by_algo_and_eta(run_dir, config):
    groups = plot.load_curves([run_dir, run_dir])  # the same run twice: each (group, seed) counts once
    (group, series), = groups.items()
    assert group == ("maze-2", "csac", (0.1, 1.0))
    assert len(series) == config.grid_size > 1
    steps = np.arange(1, config.num_epochs + 1) * config.budget.steps_per_epoch
    for s, v in series:
        np.testing.assert_array_equal(s, steps)
        assert v.shape == steps.shape


def test_load_curves_refuses_to_pool_a_seed_of_two_different_experiments(run_dir, tmp_path, capsys):
    import shutil

    other = tmp_path / "floor"
    shutil.copytree(run_dir, other)
    saved = Config.from_dict(json.loads((other / "config.json").read_text()))
    config = {**saved.flat(), "grid_size": saved.grid_size}  # written in the flat form of older runs
    (other / "config.json").write_text(json.dumps({**config, "total_steps": 10 * config["total_steps"]}))
    assert len(plot.load_curves([run_dir, other])[("maze-2", "csac", (0.1, 1.0))]) == config["grid_size"]  # resumed longer
    older = {k: v for k, v in config.items() if k != "normaliser"}  # a run from before the field existed
    (other / "config.json").write_text(json.dumps(older))
    assert len(plot.load_curves([run_dir, other])[("maze-2", "csac", (0.1, 1.0))]) == config["grid_size"]
    (other / "config.json").write_text(json.dumps({**config, "normaliser": "floor"}))
    with pytest.raises(ValueError, match="both hold csac η=0.1 seed 0 but differ in normaliser; give each run"):
        plot.load_curves([run_dir, other])
    with pytest.raises(SystemExit):
        plot.main([str(run_dir), str(other)])
    assert "differ in normaliser" in capsys.readouterr().err


def test_mean_std_over_members_of_different_lengths():
    steps, mean, std, count = plot.mean_std([(np.array([10, 20]), np.array([0.0, 1.0])),
                                             (np.array([10, 20, 30]), np.array([1.0, 0.0, 0.5]))])
    np.testing.assert_array_equal(steps, [10, 20, 30])
    np.testing.assert_allclose(mean, [0.5, 0.5, 0.5])
    np.testing.assert_allclose(std, [0.5, 0.5, 0.0])
    np.testing.assert_array_equal(count, [2, 2, 1])


def test_heatmap_and_ratio_grid(tmp_path):
    runs = []
    for i, etas in enumerate([[(0.1, 0.5), (0.5, 0.5)], [(0.1, 0.9)]]):
        run = tmp_path / f"sweep{i}"
        run.mkdir()
        members = [{"eta": [a, b, 1.0], "seed": seed, "final_success": a + b + seed} for a, b in etas for seed in (0, 1)]
        (run / "summary.json").write_text(json.dumps({"members": members}))
        runs.append(run)
    eta1, eta2, values = plot.ratio_grid(runs)
    np.testing.assert_allclose(eta1, [0.1, 0.5])
    np.testing.assert_allclose(eta2, [0.5, 0.9])
    np.testing.assert_allclose(values, [[1.1, 1.5], [1.5, np.nan]])  # mean over seeds 0, 1 adds 0.5

    fig = plot.heatmap(values / 2, eta1, eta2, title="3 rooms")
    fig.savefig(tmp_path / "heat.png")
    _decoded_png(tmp_path / "heat.png")
    with pytest.raises(ValueError, match="shape"):
        plot.heatmap(values, eta2[:1], eta1)


def test_save_figure_keeps_a_file_with_the_same_pixels(tmp_path):
    """A figure re-drawn from unchanged data leaves the PNG there as it is, even after a lossy re-compression
    (PIL's palette quantisation standing in for pngquant) that keeps the text fields; new data rewrites it."""
    from PIL import Image, PngImagePlugin

    def figure(ys):
        ax = plot.new_figure().add_subplot()
        ax.plot(ys)
        return ax.figure

    path = tmp_path / "f.png"
    assert plot.save_figure(figure([0, 1, 2]), path)
    with Image.open(path) as im:
        info = PngImagePlugin.PngInfo()
        for k, v in im.text.items():
            info.add_text(k, v)
        im.convert("RGB").quantize(64).save(path, pnginfo=info)
    quantised = path.read_bytes()
    assert not plot.save_figure(figure([0, 1, 2]), path)
    assert path.read_bytes() == quantised
    assert plot.save_figure(figure([0, 1, 3]), path)
    assert path.read_bytes() != quantised
    _decoded_png(path)
    svg = tmp_path / "f.svg"  # other formats: written as they are, every time
    assert plot.save_figure(figure([0, 1, 2]), svg) and plot.save_figure(figure([0, 1, 2]), svg)
    assert svg.read_text().lstrip().startswith("<?xml")
    broken = tmp_path / "broken.png"
    broken.write_text("not a png")
    assert plot.save_figure(figure([0, 1, 2]), broken)
    _decoded_png(broken)


def test_save_figure_and_say_reports_written_and_unchanged(tmp_path, capsys):
    path = tmp_path / "f.png"
    for expected in ("wrote", "unchanged:"):
        ax = plot.new_figure().add_subplot()
        ax.plot([0, 1, 2])
        assert plot.save_figure_and_say(ax.figure, str(path)) == path
        assert capsys.readouterr().out == f"{expected} {path}\n"


# ----- videos ------------------------------------------------------------------------------------
def test_render_cli_video_frames_change(run_dir, tmp_path):
    path = render.main([str(run_dir), "--member", "1", "--episodes", "2", "--out", str(tmp_path / "m1.gif")])
    assert path == tmp_path / "m1.gif" and path.stat().st_size > 10_000
    frames = iio.imread(path)  # [T, H, W, 3 or 4]
    assert frames.ndim == 4 and len(frames) > 10
    assert frames.shape[1:3] == (5 * 48 + 80, 10 * 48 + 96)
    assert np.any(frames[0] != frames[len(frames) // 2]) and np.any(frames[1] != frames[-1])


def test_evaluate_cli_reevaluates_every_member_from_the_checkpoint(run_dir, config, tmp_path, capsys):
    rows = evaluate.main([str(run_dir), "--episodes", "6", "--out", str(tmp_path / "det.json")])
    assert [(r["member"], r["seed"]) for r in rows] == [(0, 0), (1, 1)]
    assert json.loads((tmp_path / "det.json").read_text()) == rows
    for r in rows:
        assert r["episodes"] == 6 and not r["stochastic"] and len(r["stage_fraction"]) == config.num_stages
        assert r["stage_fraction"][0] == 1.0 and 0.0 <= r["success_rate"] <= r["stage_fraction"][-1] <= 1.0
        assert set(r["eval_end"]) == {"pocket"} and 0 < r["eval_episode_length"] <= config.task.max_episode_steps
    last = config.num_epochs  # the latest checkpoint is the default
    assert evaluate.evaluate_run(run_dir, episodes=6, epoch=last) == rows
    noisy = evaluate.evaluate_run(run_dir, episodes=6, stochastic=True)
    assert all(r["stochastic"] for r in noisy) and [r["eval_return"] for r in noisy] != [r["eval_return"] for r in rows]
    assert "| member | seed | eta | success |" in capsys.readouterr().out
    for argv, message in ((["--episodes", "0"], "episodes: must be >= 1"), (["--epoch", "99"], "no checkpoint of epoch 99"),):
        with pytest.raises(SystemExit) as exit_info:
            evaluate.main([str(run_dir)] + argv)
        assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_rollout_stops_at_done_and_maze_frames_follow_the_robot():
    env = Maze(rooms=2, episode_length=12)
    forward = jax.jit(lambda obs, stage: jnp.broadcast_to(jnp.array([1.0, 0.3]), obs.shape[:-1] + (2,)))
    eps = render.rollout(env, forward, jax.random.PRNGKey(3), n=2, max_steps=20)
    for ep in eps:
        assert ep.steps == 12 and not ep.success  # truncated by the env at episode_length
        pos = ep.states.pipeline_state.pos
        assert ep.obs.shape == (13, env.observation_size) and pos.shape == (13, 2) and ep.reward[0] == 0
        np.testing.assert_allclose(pos / [10.0, 5.0], ep.obs[:, 20:22], atol=1e-6)
        assert pos[-1, 0] > pos[0, 0] + 1.0
    frames = env.render_frames(eps[0].states)
    assert frames.shape == (13, 320, 576, 3) and frames.dtype == np.uint8
    assert all(np.any(a != b) for a, b in zip(frames[:-1], frames[1:]))


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # reading MP4 starts ffmpeg
def test_write_video_mp4_or_gif_fallback(tmp_path, monkeypatch):
    frames = np.zeros((6, 64, 96, 3), np.uint8)
    frames[np.arange(6), :, np.arange(6) * 10] = 255  # a moving bar
    if render.has_ffmpeg():
        path = render.write_video(tmp_path / "a.mp4", frames, fps=5)
        assert path.suffix == ".mp4" and len(iio.imread(path)) == 6
    monkeypatch.setattr(render, "has_ffmpeg", lambda: False)
    path = render.write_video(tmp_path / "b.mp4", frames, fps=5)
    assert path == tmp_path / "b.gif"
    decoded = iio.imread(path)
    assert len(decoded) == 6 and np.any(decoded[0] != decoded[-1])
    with pytest.raises(render.RenderError, match="mp4 or .gif"):
        render.write_video(tmp_path / "c.avi", frames, fps=5)


def test_an_env_without_render_hook_is_refused_before_rollout():
    with pytest.raises(render.RenderError, match=r"env 'toy' \(Line\) cannot be drawn: give it a method render_frames"):
        render.renderer(Line(), "toy")
    from user_env_module import make  # a StageWrapper around an env with neither a hook nor a MuJoCo model

    with pytest.raises(render.RenderError, match=r"\(Slider \(inside StageWrapper\) has no render_frames"):
        render.renderer(make(), "user_env_module:make")


def _gl_works() -> bool:
    """Whether MuJoCo can open an offscreen GL context here; probed in a child process, since a
    failing GL initialisation aborts the process instead of raising."""
    probe = ("import envs_mjx.peg_in_hole, mujoco; "
             "mujoco.Renderer(mujoco.MjModel.from_xml_string('<mujoco/>'), 8, 8)")
    return subprocess.run([sys.executable, "-c", probe], capture_output=True, timeout=300).returncode == 0


def _stacked_qpos(qpos: np.ndarray, field: str = "qpos") -> types.SimpleNamespace:
    """The part of an episode's stacked states a MuJoCo hook reads: pipeline_state.<field> [T, nq]."""
    return types.SimpleNamespace(pipeline_state=types.SimpleNamespace(**{field: qpos}))


def test_peg_frames_through_its_render_hook():
    peg = pytest.importorskip("envs_mjx.peg_in_hole")
    if not _gl_works():
        pytest.skip("no OpenGL context for MuJoCo on this machine (set MUJOCO_GL=egl or osmesa)")
    env = peg.PegInHole(episode_length=10)
    frames = env.render_frames(_stacked_qpos(np.tile(env.mj_model.qpos0, (3, 1)).astype(np.float32)))
    assert frames.shape == (3, 240, 320, 3) and frames.dtype == np.uint8 and frames.std() > 5


def test_pusher_frames_through_stage_wrapper_and_mujoco():
    if not _gl_works():
        pytest.skip("no OpenGL context for MuJoCo on this machine (set MUJOCO_GL=egl or osmesa)")
    from envs_mjx.pusher import Pusher

    env = Pusher(episode_length=10)
    model = env.env.sys.mj_model
    qpos = np.tile(model.qpos0, (2, 1)).astype(np.float32)
    qpos[1, 0] += 0.8  # the shoulder turns: the arm moves between the frames
    frames = render.renderer(env, "pusher")(_stacked_qpos(qpos, "q"))
    assert frames.shape == (2, 240, 320, 3) and frames.dtype == np.uint8 and frames.std() > 5
    assert np.abs(frames[0].astype(int) - frames[1].astype(int)).mean() > 1.0


# ----- loggers -----------------------------------------------------------------------------------
def _scalar_events(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """tag -> [(step, value)] from the TFRecord event files in `folder` (raw protobuf read)."""
    from tensorboardX.proto import event_pb2

    found: dict[str, list[tuple[int, float]]] = {}
    for path in sorted(folder.glob("events.out.tfevents.*")):
        data, i = path.read_bytes(), 0
        while i < len(data):
            (n,) = struct.unpack("<Q", data[i:i + 8])  # record: length, crc, payload, crc
            event = event_pb2.Event.FromString(data[i + 12:i + 12 + n])
            i += 12 + n + 4
            for value in event.summary.value:
                if value.WhichOneof("value") == "simple_value":
                    found.setdefault(value.tag, []).append((event.step, value.simple_value))
    return found


def test_tensorboard_logger_writes_one_folder_per_member(run_dir, config, tmp_path):
    rows = outputs.read_rows(run_dir / "metrics.jsonl")
    sink = loggers.make_loggers(tmp_path, config, tensorboard=True)
    for epoch in range(1, config.num_epochs + 1):
        sink.write([r for r in rows if r["epoch"] == epoch])
    sink.close()
    assert sorted(p.name for p in (tmp_path / "tb").iterdir()) == [f"member_{k}" for k in range(config.grid_size)]
    for member in range(config.grid_size):
        mine = [r for r in rows if r["member"] == member]
        events = _scalar_events(tmp_path / "tb" / f"member_{member}")
        assert {"success_rate", "eval_return", "q_loss/agent_0", "q_loss/agent_1", "eta_star/agent_0"} <= set(events)
        assert "eta_star/agent_1" not in events and "epoch" not in events  # undefined η*; ids are not metrics
        assert events["eval_return"] == [(r["env_steps"], pytest.approx(r["eval_return"])) for r in mine]
        assert events["pi_loss/agent_1"] == [(r["env_steps"], pytest.approx(r["pi_loss"][1])) for r in mine]


def test_wandb_is_optional_and_used_when_asked(run_dir, config, tmp_path, monkeypatch):
    sink = loggers.make_loggers(tmp_path, config, tensorboard=False)
    assert sink.sinks == []  # nothing asked for, nothing made

    monkeypatch.setitem(sys.modules, "wandb", None)  # as if not installed
    with pytest.raises(ImportError, match="pip install wandb"):
        loggers.make_loggers(tmp_path, config, tensorboard=False, wandb_project="p")

    logged = []
    fake_run = types.SimpleNamespace(log=lambda data, step: logged.append((step, data)), finish=lambda: None)
    fake = types.ModuleType("wandb")
    fake.__spec__ = importlib.machinery.ModuleSpec("wandb", None)
    fake.init = lambda **kw: fake_run
    monkeypatch.setitem(sys.modules, "wandb", fake)
    sink = loggers.make_loggers(tmp_path, config, tensorboard=False, wandb_project="p")
    rows = [r for r in outputs.read_rows(run_dir / "metrics.jsonl") if r["epoch"] == 1]
    sink.write(rows)
    sink.close()
    (step, data), = logged
    assert step == rows[0]["env_steps"] == config.budget.steps_per_epoch  # the axis TensorBoard uses
    assert data["member_1/epoch"] == 1
    assert data["member_1/success_rate"] == rows[1]["success_rate"]
    assert data["member_0/q_loss/agent_1"] == pytest.approx(rows[0]["q_loss"][1])
