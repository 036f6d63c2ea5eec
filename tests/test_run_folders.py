"""A run folder is a complete run, a resumable run, or refused with the way out named: never mixed with another
run's files. Every refusal here comes before anything is traced or compiled."""
import shutil

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
