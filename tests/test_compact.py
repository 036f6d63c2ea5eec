"""Compacted metrics (metrics.jsonl.gz): the same rows back, one reading path for both forms, finished runs only,
resume."""
import gzip
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from ccp_jax import outputs, plot
from ccp_jax.config import ConfigError, make_config

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
sys.path.insert(0, str(EXPERIMENTS))

import common  # noqa: E402
import compact_results  # noqa: E402


def _f32(x: float) -> float:
    """A float32 as the device's metrics arrive: a Python float holding a float32 value."""
    return float(np.float32(x))


def _rows() -> list[dict]:
    """Rows with every kind of value a metrics row holds."""
    return [{"member": m, "seed": 3 + m, "eta": [0.1, "auto", 1.0], "algo": "csac", "epoch": e, "env_steps": 5000 * e,
             "success_rate": _f32(0.1 * e), "q_loss": [_f32(1e-7 * e), _f32(-3.4e38), _f32(123456.789)],
             "eta_star": [_f32(0.3), None], "eval_end": {"pocket": _f32(0.7), "stage": [_f32(1 / 3), 0]},
             "q_min": [_f32(-0.0), float("nan"), float("inf")], "updated": True, "note": "é",
             "buffer_fill": 5000 * e / 200_000, "epoch_wall_s": 12.345678901234567 + e}
            for e in (1, 2, 3) for m in (0, 1)]


def _finished(folder: Path, rows: list[dict]) -> Path:
    """A finished run folder; its metrics as json writes them, bare NaN included, as older runs hold them."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    outputs.write_json(folder / "summary.json", {"members": []})
    return folder


def _same(original: list[dict], back: list[dict]) -> bool:
    """Every value the same: json's text of a row is exact (every float's repr, NaN, int or bool, key order)."""
    return [json.dumps(r) for r in original] == [json.dumps(r) for r in back]


def test_hand_made_rows_round_trip(tmp_path):
    folder = _finished(tmp_path / "run", rows := _rows())
    raw_bytes = (folder / "metrics.jsonl").stat().st_size
    before, after = outputs.compact_metrics(folder)
    assert (before, after) == (raw_bytes, (folder / "metrics.jsonl.gz").stat().st_size) and after < before
    assert not (folder / "metrics.jsonl").exists() and outputs.metrics_file(folder) == folder / "metrics.jsonl.gz"
    back = outputs.read_rows(outputs.metrics_file(folder))
    assert _same(rows, back) and math.isnan(back[0]["q_min"][1])
    first = back[0]
    assert first["epoch_wall_s"] == rows[0]["epoch_wall_s"] and first["buffer_fill"] == 0.025  # not float32: as is
    assert first["eta"] == [0.1, "auto", 1.0] and first["eta_star"][1] is None and first["updated"] is True
    assert first["eval_end"]["stage"][1] == 0 and type(first["eval_end"]["stage"][1]) is int
    text = gzip.decompress((folder / "metrics.jsonl.gz").read_bytes()).decode()
    assert '"eta_star": [0.3E0, null]' in text and "0.30000001192092896" not in text  # the shortest float32 decimal
    assert '"eta": [0.1, "auto", 1.0]' in text and '"buffer_fill": 0.025,' in text  # no float32: as json writes it


def test_read_rows_reads_both_forms_identically(tmp_path):
    raw = _finished(tmp_path / "raw", _rows())
    plain = tmp_path / "plain"  # a plain gzip of the same bytes (as experiments/paper_budget.py writes)
    plain.mkdir()
    (plain / "metrics.jsonl.gz").write_bytes(gzip.compress((raw / "metrics.jsonl").read_bytes()))
    read = lambda folder: json.dumps(outputs.read_rows(outputs.metrics_file(folder)))
    assert read(plain) == read(raw)
    assert json.dumps(outputs.read_rows(plain / "metrics.jsonl")) == read(raw)  # the raw name finds the gzip too
    # A last row without its newline is being written: left out from either form.
    text = (raw / "metrics.jsonl").read_text()
    (plain / "metrics.jsonl.gz").write_bytes(gzip.compress(text[: text.rindex("{") + 30].encode()))
    assert outputs.read_rows(plain / "metrics.jsonl.gz") == outputs.read_rows(raw / "metrics.jsonl")[:-1]
    lines = text.splitlines(keepends=True)
    lines[2] = lines[2][:20] + "\n"
    (plain / "metrics.jsonl.gz").write_bytes(gzip.compress("".join(lines).encode()))
    with pytest.raises(ConfigError, match=r"^resume: .*metrics.jsonl.gz line 3 is not a JSON row"):
        outputs.read_rows(outputs.metrics_file(plain), field="resume")
    (plain / "metrics.jsonl.gz").write_bytes(b"not a gzip")
    with pytest.raises(ConfigError, match=r"^run_dir: .*metrics.jsonl.gz is not a readable gzip file"):
        outputs.read_rows(plain / "metrics.jsonl")
    assert outputs.metrics_file(tmp_path / "nothing") == tmp_path / "nothing" / "metrics.jsonl"


def test_compacting_is_deterministic_and_idempotent(tmp_path):
    a, b = _finished(tmp_path / "a", _rows()), _finished(tmp_path / "b", _rows())
    outputs.compact_metrics(a)
    outputs.compact_metrics(b)
    packed = (a / "metrics.jsonl.gz").read_bytes()
    assert (b / "metrics.jsonl.gz").read_bytes() == packed
    assert outputs.compact_metrics(a) == (len(packed), len(packed)) and (a / "metrics.jsonl.gz").read_bytes() == packed
    plain = _finished(tmp_path / "plain", _rows())  # a plain gzip is rewritten compactly, to the same bytes
    (plain / "metrics.jsonl.gz").write_bytes(gzip.compress((plain / "metrics.jsonl").read_bytes()))
    (plain / "metrics.jsonl").unlink()
    outputs.compact_metrics(plain)
    assert (plain / "metrics.jsonl.gz").read_bytes() == packed


def test_an_unfinished_run_is_refused_and_nothing_changes(tmp_path):
    folder = _finished(tmp_path / "run", _rows())
    (folder / "summary.json").unlink()
    before = (folder / "metrics.jsonl").read_bytes()
    with pytest.raises(ConfigError, match="^run_dir: .* has no summary.json: only a finished run"):
        outputs.compact_metrics(folder)
    outputs.write_json(folder / "summary.json", {})
    (folder / "metrics.jsonl").write_bytes(cut := before[:-10])  # finished, but its last row cut
    with pytest.raises(ConfigError, match="last row has no newline"):
        outputs.compact_metrics(folder)
    assert (folder / "metrics.jsonl").read_bytes() == cut and not (folder / "metrics.jsonl.gz").exists()


def test_a_committed_run_reads_back_the_same_summary_and_curves(tmp_path):
    committed = EXPERIMENTS / "results" / "table1_cpu" / "peg" / "sac"
    folder = tmp_path / "sac"
    shutil.copytree(committed, folder)
    config = outputs.read_config(folder)
    saved = json.loads((folder / "summary.json").read_text())
    rows, curves = outputs.read_rows(outputs.metrics_file(folder)), plot.load_curves([folder])
    outputs.compact_metrics(folder)
    assert not (folder / "metrics.jsonl").exists()
    assert _same(rows, outputs.read_rows(outputs.metrics_file(folder)))
    summary = outputs.summarise(config, outputs.read_rows(outputs.metrics_file(folder)), wall_s=saved["wall_s"])
    assert outputs.summary_table(summary) == outputs.summary_table(saved)
    assert [m["final_success"] for m in summary["members"]] == [m["final_success"] for m in saved["members"]]
    after = plot.load_curves([folder])
    assert curves.keys() == after.keys()
    for group in curves:
        for (s1, v1), (s2, v2) in zip(curves[group], after[group], strict=True):
            np.testing.assert_array_equal(s1, s2)
            np.testing.assert_array_equal(v1, v2)


def test_run_grid_compacts_a_finished_run(tmp_path, monkeypatch):
    from ccp_jax import train

    def fake_run(config, out, **_):
        rows = [{"member": 0, "seed": 0, "eta": [0.1, 1.0], "algo": "csac", "epoch": 1, "env_steps": 200,
                 "success_rate": _f32(0.3), "eval_return": _f32(1.5), "epoch_wall_s": 0.123456789}]
        outputs.write_rows(out / "metrics.jsonl", rows)
        summary = outputs.summarise(config, rows, wall_s=1.0)
        outputs.write_json(out / "summary.json", summary)
        return summary

    monkeypatch.setattr(train, "run", fake_run)
    monkeypatch.setattr(train, "enable_compile_cache", lambda: None)
    out = tmp_path / "maze2" / "csac"
    common.run_grid(make_config("tiny", seeds=(0,), total_steps=200), out, log=lambda *_: None)
    assert not (out / "metrics.jsonl").exists()
    assert outputs.read_rows(outputs.metrics_file(out))[0]["success_rate"] == _f32(0.3)


def test_compact_results_compacts_finished_runs_once(tmp_path, capsys):
    _finished(tmp_path / "a" / "done", _rows())
    running = _finished(tmp_path / "b" / "running", _rows())
    (running / "summary.json").unlink()
    before, after = compact_results.main(compact_results.Args(root=tmp_path))
    assert after < before and (tmp_path / "a" / "done" / "metrics.jsonl.gz").exists()
    assert (running / "metrics.jsonl").exists() and not (running / "metrics.jsonl.gz").exists()
    packed = (tmp_path / "a" / "done" / "metrics.jsonl.gz").read_bytes()
    assert compact_results.main(compact_results.Args(root=tmp_path)) == (after, after)
    assert (tmp_path / "a" / "done" / "metrics.jsonl.gz").read_bytes() == packed
    out = capsys.readouterr().out.splitlines()
    assert "a/done: compacted already" in out and "b/running: no summary.json (still training?), left as it is" in out


def test_resuming_a_compacted_run_restores_its_raw_metrics(tmp_path):
    from ccp_jax.train import main, run

    config = make_config("tiny", etas=((0.1,),), seeds=(0,), total_steps=400)
    out = tmp_path / "run"
    run(config, out, progress=False, checkpoint_every=1, tensorboard=False)
    original = (out / "metrics.jsonl").read_text()
    outputs.compact_metrics(out)
    main(["--resume", str(out), "--total-steps", "600", "--no-progress"])
    assert not (out / "metrics.jsonl.gz").exists()
    assert (out / "metrics.jsonl").read_text().startswith(original)  # the same bytes, then epoch 3's row
    assert [r["epoch"] for r in outputs.read_rows(out / "metrics.jsonl")] == [1, 2, 3]


def test_non_finite_values_are_written_as_strict_json_null(tmp_path):
    """A diverged loss (NaN, inf) is null in metrics.jsonl and summary.json, which strict parsers accept; a critic
    that went NaN still counts as diverged when the rows are read back."""
    rows = [dict(member=0, epoch=1, env_steps=10, q_loss=[float("nan")], pi_loss=[np.float32("inf")],
                 q_max=[1.0, float("nan")], arr=np.array([1.5, -np.inf]))]
    outputs.write_rows(tmp_path / "m.jsonl", rows)
    outputs.append_rows(tmp_path / "m.jsonl", rows)
    outputs.write_json(tmp_path / "s.json", {"peak": float("-inf"), "ok": np.float64(2.5)})
    strict = lambda text: json.loads(text, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    back = [strict(line) for line in (tmp_path / "m.jsonl").read_text().splitlines()]
    assert back[0] == back[1] == dict(member=0, epoch=1, env_steps=10, q_loss=[None], pi_loss=[None],
                                      q_max=[1.0, None], arr=[1.5, None])
    assert strict((tmp_path / "s.json").read_text()) == {"peak": None, "ok": 2.5}
    peaks = outputs.critic_peaks(back, limit=100.0)
    assert peaks["q_diverged_env_steps"] == 10 and peaks["q_peak"][0] == 1.0 and np.isnan(peaks["q_peak"][1])
