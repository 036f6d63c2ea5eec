"""experiments/paper_budget.py's queue and folders, what it keeps of a finished grid (one shrunken training run),
and its report on hand-made runs."""
import gzip
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import paper_budget  # noqa: E402
import paper_budget_report as report  # noqa: E402


def _rows(seed: int, member: int, success: list[float], pocket: float = 0.0) -> list[dict]:
    return [dict(member=member, seed=seed, epoch=e, env_steps=e * 5000, success_rate=s,
                 stage_reached_mean=s, eval_end={"pocket": pocket}) for e, s in enumerate(success, start=1)]


def _write(folder: Path, rows: list[dict], packed: bool) -> None:
    folder.mkdir(parents=True)
    text = "".join(json.dumps(r) + "\n" for r in rows)
    if packed:
        with gzip.open(folder / "metrics.jsonl.gz", "wt") as f:
            f.write(text)
    else:
        (folder / "metrics.jsonl").write_text(text + '{"member": 0, "epo')  # a row still being written


def test_queue_orders_the_informative_cells_first_and_names_are_unique():
    keys = [cell.key for cell in paper_budget.QUEUE]
    assert keys[:3] == ["maze2/sac", "maze2/naive", "maze2/csac_0.1"]
    assert len(set(keys)) == len(keys)
    assert paper_budget.SEEDS == (30, 31, 32, 33, 34)
    ramp = paper_budget.CELLS["maze4/csac_ramp"]
    assert ramp.etas == ((0.1, 0.3, 0.5),) and ramp.rooms == 4
    assert keys[-1] == "maze4/csac_0.1"  # an extra cell, after the issue's
    # the report's "our ratio" is a domain's first CSAC cell in the queue: on 4 rooms it stays η = 0.5
    assert next(c for c in paper_budget.QUEUE if c.domain == "maze4" and c.algo == "csac").name == "csac_0.5"


def test_seed_chunks_and_their_folders(tmp_path):
    args = paper_budget.Args(seeds_per_grid=3, out=tmp_path)
    assert args.chunks() == [(30, 31, 32), (33, 34)]
    cell = paper_budget.CELLS["maze3/naive"]
    assert paper_budget.grid_folder(tmp_path, cell, (33, 34)) == tmp_path / "maze3" / "naive_seeds33to34"
    assert paper_budget.grid_folder(tmp_path, cell, paper_budget.SEEDS) == tmp_path / "maze3" / "naive"
    assert paper_budget.Args(total_steps=1000, out=tmp_path).folder == tmp_path / "budget_1000"
    with pytest.raises(SystemExit, match="cells"):
        paper_budget.Args(cells=("maze9/sac",)).chosen()
    with pytest.raises(SystemExit, match="seeds_per_grid"):
        paper_budget.Args(seeds_per_grid=0).chunks()


def test_a_finished_grid_keeps_its_final_policies_and_drops_its_checkpoints(tmp_path, monkeypatch):
    """The queue's train step on a shrunken cell (tiny networks and epochs, two seeds), stopped right after the
    training (before the export): the checkpoints are still there; the next call finds the grid finished, writes
    one exported chain per member to policies/ (which runs with jax alone) and only then deletes them."""
    import jax

    from ccp_jax.config import PRESETS

    tiny = {k: PRESETS["tiny"][k] for k in ("hidden", "batch_size", "buffer_size", "steps_per_epoch",
                                             "train_loops_per_epoch", "start_steps", "max_episode_steps",
                                             "eval_episodes", "num_envs")}
    monkeypatch.setattr(paper_budget, "SETTINGS", tiny)
    real_run_grid = paper_budget.run_grid

    def stopped_after_training(*a, **k):
        real_run_grid(*a, **k)
        raise KeyboardInterrupt

    monkeypatch.setattr(paper_budget, "run_grid", stopped_after_training)
    args = paper_budget.Args(cells=("maze2/sac",), seeds=(30, 31), total_steps=400, out=tmp_path)
    folder = paper_budget.grid_folder(args.folder, paper_budget.CELLS["maze2/sac"], (30, 31))
    assert folder == tmp_path / "budget_400" / "maze2" / "sac_seeds30to31"
    with pytest.raises(KeyboardInterrupt):
        paper_budget.train(args)
    assert (folder / "checkpoints").is_dir() and (folder / "summary.json").exists()
    assert not (folder / "policies").exists()

    paper_budget.train(args)  # finds it finished: exports, then deletes
    assert not (folder / "checkpoints").exists() and (folder / "metrics.jsonl.gz").exists()
    assert sorted(p.name for p in (folder / "policies").iterdir()) == [
        "member0.jaxexport", "member0.json", "member1.jaxexport", "member1.json"]
    meta = json.loads((folder / "policies" / "member1.json").read_text())
    assert (meta["seed"], meta["num_stages"]) == (31, 2)
    policy = jax.export.deserialize(bytearray((folder / "policies" / "member1.jaxexport").read_bytes()))
    action = np.asarray(policy.call(np.zeros((3, meta["obs_size"]), np.float32), np.zeros((3,), np.int32)))
    assert action.shape == (3, meta["action_size"]) and np.all(np.abs(action) <= 1.0)


def test_report_pools_chunks_and_measures_each_seed(tmp_path):
    """Two chunks of SAC (one finished and packed, one still writing) and Naive: finals, learnt-at, decay."""
    learns = [0.0] * 10 + [1.0] * 20  # running success reaches 0.5 at epoch 15 (env step 75 000)
    decays = [1.0] * 20 + [0.0] * 10  # peak 1.0, final 0.0
    _write(tmp_path / "maze2" / "sac_seeds30to31", _rows(30, 0, learns) + _rows(31, 1, [0.0] * 30, 1.0), True)
    _write(tmp_path / "maze2" / "sac_seeds32to34", _rows(32, 0, learns), False)
    _write(tmp_path / "maze2" / "naive", _rows(30, 0, decays) + _rows(31, 1, learns), True)
    _write(tmp_path / "maze2" / "sac_other", _rows(99, 0, learns), True)  # not a chunk of sac: ignored

    sac = report.load_cell(tmp_path, paper_budget.CELLS["maze2/sac"])
    assert [m.seed for m in sac] == [30, 31, 32]
    assert [m.final for m in sac] == [1.0, 0.0, 1.0]
    assert [m.solved_at for m in sac] == [75_000, None, 75_000]
    assert sac[1].end() == "31: room 1.0, 100% pocket"

    naive = report.load_cell(tmp_path, paper_budget.CELLS["maze2/naive"])
    row = report.cell_row(paper_budget.CELLS["maze2/naive"], naive)
    assert row["finals"] == [0.0, 1.0]
    np.testing.assert_allclose(row["peak"], [1.0, 1.0])
    np.testing.assert_allclose(row["drop"], [1.0, 0.0], atol=1e-12)
    assert row["paper"] == 0.54 and row["solved"] == 1

    text = report.report(tmp_path)
    assert "| maze2 | SAC | 150,000 | 3 | 0.67 [" in text
    assert (tmp_path / "curves_maze2.png").stat().st_size > 0
    assert "never" in (tmp_path / "table.csv").read_text()
