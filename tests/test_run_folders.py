"""A run folder is a complete run, a resumable run, or refused with the way out named: never mixed with another
run's files. Every refusal here comes before anything is traced or compiled."""
import shutil
import types

import pytest

from ccp_jax import checkpoint
from ccp_jax.config import ConfigError
from ccp_jax.train import main

TINY = ["--preset", "tiny", "--no-progress", "--no-tensorboard"]


def test_out_at_or_under_a_file_is_refused(tmp_path):
    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    with pytest.raises(ConfigError, match=r"^out: .*notes.txt is a file, not a folder"):
        main(TINY + ["--out", str(afile)])
    with pytest.raises(ConfigError, match=r"^out: cannot create .*notes.txt/run"):
        main(TINY + ["--out", str(afile / "run")])
    assert afile.read_text() == "mine"


def test_another_runs_checkpoints_in_out_are_refused_not_mixed(tmp_path):
    """Copying a run's checkpoints into a new folder used to train around them (orbax skipped the steps they
    held), and `evaluate` then read the other run's policy."""
    out = tmp_path / "y"
    (out / checkpoint.CHECKPOINT_DIR / "9").mkdir(parents=True)
    with pytest.raises(ConfigError, match=r"^out: .* already holds a run \(checkpoints\)"):
        main(TINY + ["--out", str(out)])
    assert sorted(p.name for p in (out / checkpoint.CHECKPOINT_DIR).iterdir()) == ["9"]
    (out / checkpoint.CHECKPOINT_DIR / "9").rmdir()  # an empty checkpoints folder holds nothing to mix
    shutil.rmtree(out)


@pytest.mark.parametrize("name", ["summary.json", "metrics.jsonl.gz"])
def test_a_finished_or_compacted_run_is_refused(tmp_path, name):
    out = tmp_path / "done"
    out.mkdir()
    (out / name).write_text("{}")
    with pytest.raises(ConfigError, match=rf"^out: .* already holds a run \({name}\)"):
        main(TINY + ["--out", str(out)])


def test_resume_at_a_file_names_the_argument(tmp_path):
    afile = tmp_path / "run.txt"
    afile.write_text("x")
    with pytest.raises(ConfigError, match=r"^resume: .*run.txt holds no run \(no config.json\)"):
        main(TINY + ["--resume", str(afile)])


def test_resume_keeps_the_checkpoint_interval_the_run_started_with(tmp_path):
    """--checkpoint-every lives in run.json; --resume without it used to fall back to 10."""
    out = tmp_path / "run"
    main(TINY + ["--total-steps", "600", "--checkpoint-every", "1", "--out", str(out)])
    assert (out / "run.json").read_text().count('"checkpoint_every": 1') == 1
    main(TINY + ["--resume", str(out), "--total-steps", "1200"])
    mngr = checkpoint.manager(out)
    assert mngr.all_steps() == [5, 6]  # every epoch checkpointed (2 kept); with an interval of 10 only 6
    mngr.close()


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A tiny run of 5 epochs of 200 steps, checkpointed every epoch (the last 2 kept: 4 and 5), with TensorBoard."""
    out = tmp_path_factory.mktemp("runs") / "finished"
    main(["--preset", "tiny", "--no-progress", "--total-steps", "1000", "--checkpoint-every", "1", "--out", str(out)])
    return out


def _copy(run, tmp_path, keep_rows=None):
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    if keep_rows is not None:
        lines = (copy / "metrics.jsonl").read_text().splitlines(keepends=True)
        (copy / "metrics.jsonl").write_text("".join(lines[:keep_rows]))
    return copy


def _events(run):
    return sorted(p.name for p in (run / "tb").rglob("events.*"))


def test_resume_past_a_hole_in_the_metrics_is_refused(finished, tmp_path):
    """Rows ending before the oldest checkpoint used to resume from the latest one and exit 0, epochs missing."""
    run = _copy(finished, tmp_path, keep_rows=2)  # epochs 1-2 of 5; checkpoints 4 and 5
    events = _events(run)
    with pytest.raises(ConfigError, match=r"^resume: metrics.jsonl in .* holds epochs 1-2, but its oldest "
                                          r"checkpoint is of epoch 4: resuming would leave epochs 3-4 without"):
        main(["--resume", str(run), "--no-progress"])
    assert _events(run) == events  # a refused resume logs nothing
    assert checkpoint.manager(run).all_steps() == [4, 5]


def test_resume_with_its_metrics_deleted_is_refused(finished, tmp_path):
    run = _copy(finished, tmp_path)
    (run / "metrics.jsonl").unlink()
    with pytest.raises(ConfigError, match=r"^resume: .*run has no metrics.jsonl: not a run folder, or its "
                                          r"metrics were deleted"):
        main(TINY + ["--resume", str(run)])


def test_epochs_trained_again_after_a_resume_are_hidden_in_tensorboard(finished, tmp_path):
    """A run stopped after epoch 5's row but before a checkpoint covering it trains epoch 5 again from
    checkpoint 4; TensorBoard purges the first run's points from that step on instead of drawing them twice."""
    run = _copy(finished, tmp_path, keep_rows=4)
    main(["--resume", str(run), "--no-progress"])
    first, again = sorted((run / "tb" / "member_0").glob("events.*"))
    restart = 4 * 200 + 1
    purges = [e.step for e in _read_events(again) if e.HasField("session_log") and e.session_log.status == 1]
    assert purges == [restart]
    steps = [e.step for e in _read_events(again) if e.HasField("summary")
             and e.summary.value[0].tag == "success_rate"]
    assert steps == [1000]  # epoch 5 logged again, after the purge
    assert max(e.step for e in _read_events(first) if e.HasField("summary")) == 1000  # the hidden point


def _read_events(path):
    """The events of a TensorBoard event file (TFRecord framing: length, its CRC, the record, its CRC)."""
    import struct

    from tensorboardX.proto import event_pb2

    data, i = path.read_bytes(), 0
    while i < len(data):
        (n,) = struct.unpack("<Q", data[i:i + 8])
        event = event_pb2.Event()
        event.ParseFromString(data[i + 12:i + 12 + n])
        yield event
        i += 12 + n + 4


def test_a_damaged_newest_checkpoint_gives_way_to_the_older_one(finished, tmp_path, capsys):
    """Its bytes overwritten, checkpoint 5 cannot be read: the resume warns, restores checkpoint 4 and trains
    epoch 5 again, to the rows of the undamaged run."""
    run = _copy(finished, tmp_path)
    biggest = max((p for p in (run / "checkpoints" / "5" / "state").rglob("*") if p.is_file()),
                  key=lambda p: p.stat().st_size)
    data = bytearray(biggest.read_bytes())
    data[len(data) // 3: 2 * len(data) // 3] = bytes(len(data[len(data) // 3: 2 * len(data) // 3]))
    biggest.write_bytes(bytes(data))
    main(["--resume", str(run), "--no-progress"])
    assert "/checkpoints/5 cannot be restored" in capsys.readouterr().out
    again = max((run / "tb" / "member_0").glob("events.*"))  # TensorBoard restarts after checkpoint 4, not 5
    assert [e.step for e in _read_events(again) if e.HasField("session_log") and e.session_log.status == 1] == [801]
    strip = lambda path: [line.split(', "epoch_wall_s"')[0] for line in path.read_text().splitlines()]  # noqa: E731
    assert strip(run / "metrics.jsonl") == strip(finished / "metrics.jsonl")
    assert checkpoint.manager(run).all_steps() == [4, 5]


def test_a_full_disk_is_said_with_the_way_out(monkeypatch, capsys):
    """TensorStore reports a full disk as a ValueError deep in orbax; the CLI says it in one line."""
    import errno

    from ccp_jax import train

    class Full:
        directory = "/runs/x/checkpoints"

        def save(self, *args, **kwargs):
            raise ValueError('RESOURCE_EXHAUSTED: Failed writing: "/runs/x/checkpoints/4.orbax-checkpoint-tmp"')

    monkeypatch.setattr(checkpoint, "_keyed", lambda tree: {})  # the state never reaches the full disk
    with pytest.raises(OSError) as err:
        checkpoint.save(Full(), 4, state=types.SimpleNamespace(agents=types.SimpleNamespace(actor=None)))
    assert err.value.errno == errno.ENOSPC and err.value.filename == "/runs/x/checkpoints/4"

    def full(argv=None):
        raise err.value

    monkeypatch.setattr(train, "main", full)
    with pytest.raises(SystemExit, match=r"^error: out: no space left on the device \(/runs/x/checkpoints/4\); "
                                         r"the folder keeps its last checkpoint: free space .* --resume"):
        train.cli()
