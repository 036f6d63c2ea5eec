"""The experiment scripts' bookkeeping on hand-made run folders: tables, best ratio, resume rules, figures."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))

import common  # noqa: E402
import compare  # noqa: E402
import curves  # noqa: E402
import independent_ratios  # noqa: E402
import paper_budget  # noqa: E402
import pbt_compare  # noqa: E402
import peg_budget  # noqa: E402
import table1  # noqa: E402
from ccp_jax.config import ConfigError  # noqa: E402


def _fake_run(folder: Path, config, success_by_member: dict[int, list[float]]) -> None:
    """config.json, metrics.jsonl and summary.json as a finished run writes them, with given eval successes."""
    from ccp_jax import outputs

    folder.mkdir(parents=True)
    outputs.write_json(folder / "config.json", config.to_dict())
    rows = []
    for member, (eta, seed) in enumerate(config.members):
        for epoch, s in enumerate(success_by_member[member], start=1):
            rows.append(dict(member=member, seed=seed, eta=list(eta), algo=config.algo, epoch=epoch,
                             env_steps=epoch * config.budget.steps_per_epoch, success_rate=s, eval_return=10.0 * s,
                             stage_reached_mean=s * (config.num_stages - 1),  # a success ends in the last stage
                             stage_fraction=[1.0] + [s] * (config.num_stages - 1),
                             eval_end={"pocket": 1.0 - s},  # and a failure in the pocket
                             eta_star=[0.9 - 0.1 * epoch] * (config.num_stages - 1) + [None]))
    outputs.write_rows(folder / "metrics.jsonl", rows)
    outputs.write_json(folder / "summary.json", outputs.summarise(config, rows, wall_s=1.0))


@pytest.fixture()
def maze2_runs(tmp_path):
    scale = common.SCALES["smoke"]
    out = tmp_path / "table1"
    csac = scale.config("maze2", "csac", etas=[(0.1,), ("auto",)])  # members: (0.1, s0), (0.1, s1), (auto, s0), (auto, s1)
    _fake_run(out / "maze2" / "csac", csac, {0: [0, 1, 1], 1: [0, 0, 0], 2: [1, 1, 1], 3: [0, 1, 1]})
    sac = scale.config("maze2", "sac", etas=[(1.0,)])
    _fake_run(out / "maze2" / "sac", sac, {0: [0, 0, 0], 1: [0, 0, 1]})
    return out


def test_table_cells_are_mean_std_over_seeds_next_to_the_paper(maze2_runs):
    text = table1.write_table(maze2_runs, ("maze2",), ("csac", "sac", "naive"), "smoke")
    lines = text.splitlines()
    # Final success is the mean over the (three) logged epochs: seed 0 → 2/3, seed 1 → 0.
    assert "| CSAC | 0.1 | 0.33 ± 0.33 (1.00) |" in lines
    assert "| CSAC | auto | 0.83 ± 0.17 (–) |" in lines
    assert "| SAC |  | 0.17 ± 0.17 (1.00) |" in lines
    assert not any(line.startswith("| Naive") for line in lines)  # not run: no row
    # With intervals: 2 seeds' finals (0.67, 0) resample to means 0, 0.33, 0.67; P(η = 0.1 > SAC's (0, 0.33)):
    # pairs 0.67 > 0, 0.67 > 0.33, 0 = 0 (a half), 0 < 0.33 -> 2.5 / 4.
    assert "| CSAC | 0.1 | IQM 0.33 [0.00, 0.67], mean 0.33 [0.00, 0.67] |" in lines
    assert any(line.startswith("| maze2 | CSAC η = 0.1 | SAC | 0.62 [") for line in lines)
    # Where episodes end, per seed (1-based stage): seed 0 of η = 0.1 succeeded in 2 of 3 evaluations.
    where = lines[lines.index("## Where the evaluation episodes end"):]
    assert "| CSAC | 0.1 | 1.7 1.0 |" in where
    assert "| CSAC | 0.1 | 0.3 1.0 |" in where[where.index("| CSAC | 0.1 | 1.7 1.0 |") + 1:]  # the pocket table
    csv_rows = (maze2_runs / "table.csv").read_text().splitlines()
    assert csv_rows[0].startswith("algo,eta,domain,seeds,success_mean")
    row = next(r for r in csv_rows if r.startswith("csac,0.1,maze2"))
    assert ",0.333,0.333,0.67 0.00,1," in row and row.endswith(",1.67 1.00,0.33 1.00")  # per seed


def test_best_ratio_ignores_auto_and_curves_are_drawn(maze2_runs):
    summary = common.read_json(maze2_runs / "maze2" / "csac" / "summary.json")
    assert common.best_swept_eta(summary) == (0.1, 1.0)  # auto (0.83) is not a swept ratio
    tie = dict(members=[dict(eta=[e, 1.0], final_success=0.0, final_return=r) for e, r in ((0.1, 5.0), (0.9, 7.0))])
    assert common.best_swept_eta(tie) == (0.9, 1.0)  # all at 0.00: the one that got furthest
    groups = curves.domain_groups(maze2_runs, "maze2", ("csac", "sac"), with_auto=True)
    assert {(g[1], g[2]) for g in groups} == {("csac", (0.1, 1.0)), ("csac", ("auto", 1.0)), ("sac", (1.0,))}
    stage2 = curves.domain_groups(maze2_runs, "maze2", ("csac", "sac"), with_auto=True, metric=curves.STAGE2)
    assert stage2.keys() == groups.keys()
    assert all(0.0 <= v <= 1.0 for series in stage2.values() for s in series for v in s[1])
    written = curves.main(curves.Args(scale="smoke", domains=("maze2",), algos=("csac", "sac"), out=maze2_runs,
                                      plot_only=True))
    assert [p.name for p in written] == ["curves_maze2.png", "stage2_maze2.png", "curves.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in written)
    _fake_run(common.swept_folder(maze2_runs, "maze2", (0.5,)),
              common.SCALES["smoke"].config("maze2", "csac", etas=[(0.5,)]), {0: [0, 0, 0], 1: [0, 0, 0]})
    every = curves.domain_groups(maze2_runs, "maze2", ("csac",), with_auto=False, all_etas=True)
    assert {g[2] for g in every} == {(0.1, 1.0), (0.5, 1.0)}  # every swept ratio, auto only when asked
    assert set(curves.domain_groups(maze2_runs, "maze2", ("csac",), with_auto=False)) == {("maze-2", "csac", (0.1, 1.0))}
    written = curves.main(curves.Args(scale="smoke", domains=("maze2",), algos=("csac", "sac"), out=maze2_runs,
                                      plot_only=True, all_etas=True))
    assert [p.name for p in written] == ["curves_all_maze2.png", "stage2_all_maze2.png", "curves_all.png"]


def test_subset_sweeps_join_the_table_curves_and_eta_auto_rows_once(maze2_runs):
    """csac_etas_* runs (table1.py --etas) add their ratios; an (η, seed) already in csac/ keeps csac/'s value."""
    import eta_auto

    scale = common.SCALES["smoke"]
    subset = common.swept_folder(maze2_runs, "maze2", (0.1, 0.5))
    assert subset == maze2_runs / "maze2" / "csac_etas_0.1-0.5"
    _fake_run(subset, scale.config("maze2", "csac", etas=[(0.1,), (0.5,)]),
              {0: [1, 1, 1], 1: [1, 1, 1], 2: [1, 1, 1], 3: [0, 1, 1]})  # (0.1, s0), (0.1, s1), (0.5, s0), (0.5, s1)
    assert common.swept_runs(maze2_runs, "maze2") == [maze2_runs / "maze2" / "csac", subset]
    lines = table1.write_table(maze2_runs, ("maze2",), ("csac", "sac"), "smoke").splitlines()
    assert "| CSAC | 0.1 | 0.33 ± 0.33 (1.00) |" in lines  # csac/'s seeds, not the subset's repeats
    assert "| CSAC | 0.5 | 0.83 ± 0.17 (0.05) |" in lines
    assert "| CSAC | auto | 0.83 ± 0.17 (–) |" in lines
    groups = curves.domain_groups(maze2_runs, "maze2", ("csac",), with_auto=False)
    assert list(groups) == [("maze-2", "csac", (0.5, 1.0))] and len(groups[("maze-2", "csac", (0.5, 1.0))]) == 2
    # Seeds 1.00 and 0.67: their resampled means are 1.00, 0.83 or 0.67, so the interval spans both seeds.
    assert eta_auto.domain_rows(maze2_runs, "maze2")[0].startswith(
        "| maze2 | best swept η = 0.5 | 0.83 [0.67, 1.00] | 0.83 [0.67, 1.00] | 1.00 0.67 |")


def test_merged_summary_refuses_to_pool_a_member_of_two_different_experiments(maze2_runs):
    scale = common.SCALES["smoke"]
    csac = maze2_runs / "maze2" / "csac"
    floor = maze2_runs / "maze2" / "csac_floor"
    _fake_run(floor, scale.config("maze2", "csac", etas=[(0.1,)], normaliser="floor"), {0: [1, 1, 1], 1: [1, 1, 1]})
    with pytest.raises(ValueError, match="seed 0 but differ in normaliser"):
        common.merged_summary([csac, floor])
    longer = maze2_runs / "maze2" / "csac_longer"  # grid and budget may differ: the first folder's member counts
    _fake_run(longer, scale.config("maze2", "csac", etas=[(0.1,)], total_steps=2 * scale.config("maze2", "csac").budget.total_steps),
              {0: [1] * 6, 1: [1] * 6})
    members = common.merged_summary([csac, longer])["members"]
    assert len(members) == 4 and all(m["run"] == str(csac) for m in members)


def test_run_grid_skips_a_finished_run_and_refuses_another_config(maze2_runs):
    folder = maze2_runs / "maze2" / "csac"
    config = common.Config.from_dict(json.loads((folder / "config.json").read_text()))
    before = (folder / "metrics.jsonl").read_bytes()
    summary = common.run_grid(config, folder, log=lambda *_: None)
    assert summary == common.read_json(folder / "summary.json")
    with pytest.raises(ConfigError, match="^total_steps: .* holds a run with 400"):
        common.run_grid(config.replace(total_steps=800), folder, log=lambda *_: None)
    assert (folder / "metrics.jsonl").read_bytes() == before


def test_independent_ratio_report_names_the_best_pair(tmp_path):
    config = independent_ratios.pairs_config("smoke")
    assert [eta for eta, _ in config.members] == [(0.1, 0.1, 1.0), (0.1, 1.0, 1.0), (1.0, 0.1, 1.0), (1.0, 1.0, 1.0)]
    folder = tmp_path / "pairs"
    _fake_run(folder, config, {0: [0, 0], 1: [1, 1], 2: [0, 1], 3: [0, 0]})
    cells = independent_ratios.plot.ratio_cells([folder])
    text = independent_ratios.report(cells, None, "smoke", tmp_path, 400)
    assert "| best pair (η1, η2) | (0.1, 1.0) | 1.00 [1.00, 1.00] | 1.00 [1.00, 1.00] | (0.1, 1.0): 0.78 |" in text
    assert "| 1 | 0.50 ± 0.00 | 0.00 ± 0.00 |" in text
    eta1, eta2, values = independent_ratios.plot.ratio_grid([folder])
    np.testing.assert_allclose(values, [[0.0, 1.0], [0.5, 0.0]])


def test_independent_ratio_subset_joins_the_shared_diagonal_once(tmp_path):
    """A --pairs run and table1's shared ratios make one grid; auto members and repeated (pair, seed) are dropped."""
    pairs = independent_ratios.parse_pairs(["0.1,1.0", "1,0.1"])
    assert pairs == [(0.1, 1.0), (1.0, 0.1)]
    folder = independent_ratios.pairs_folder(tmp_path, pairs)
    assert folder.name == "csac_pairs_0.1-1_1-0.1"
    _fake_run(folder, independent_ratios.pairs_config("smoke", pairs), {0: [1, 1], 1: [0, 1]})  # one seed each
    shared = tmp_path / "table1" / "maze3" / "csac"
    config = common.SCALES["smoke"].config("maze3", "csac", etas=[(0.1,), ("auto",)])
    _fake_run(shared, config, {0: [0, 0], 1: [0, 1], 2: [1, 1], 3: [1, 1]})
    _fake_run(tmp_path / "maze3" / "csac_pairs", independent_ratios.pairs_config("smoke", [(0.1, 0.1)]),
              {0: [1, 1]})  # seed 0 of the shared run's η = 0.1 as well: the pairs run's value is kept
    cells = independent_ratios.plot.ratio_cells([tmp_path / "maze3" / "csac_pairs", folder, shared])
    assert cells == {(0.1, 1.0): [1.0], (1.0, 0.1): [0.5], (0.1, 0.1): [1.0, 0.5]}
    text = independent_ratios.main(independent_ratios.Args(scale="smoke", out=tmp_path, table1_out=tmp_path / "table1",
                                                           table_only=True))
    # Seeds 0.0 and 0.5: resampled means 0, 0.25 or 0.5.
    assert "| best shared η (table1.py) | 0.1 | 0.25 [0.00, 0.50] | 0.25 [0.00, 0.50] | 0.1: 0.54 |" in text
    assert "| 1 | 0.50 ± 0.00 |  |" in text and "1/2 seeds per pair" in text
    assert (tmp_path / "heatmap.png").read_bytes()[:4] == b"\x89PNG"
    for bad in (["0.1"], ["0.1,auto"], ["0.1,x"]):
        with pytest.raises(ConfigError, match="^pairs: "):
            independent_ratios.parse_pairs(bad)


def test_tp_needs_the_domains_naive_run_as_primitives(tmp_path):
    with pytest.raises(SystemExit, match="tp needs the Naive run of maze2"):
        table1.train_domain("smoke", "maze2", ("tp",), tmp_path)
    assert not (tmp_path / "maze2" / "tp").exists()
    naive = common.SCALES["smoke"].config("maze2", "naive", etas=[(1.0,)])
    _fake_run(tmp_path / "maze2" / "naive", naive, {0: [0, 0], 1: [0, 1]})  # finished, checkpoints deleted
    with pytest.raises(SystemExit, match="tp needs the checkpoints of"):
        table1.train_domain("smoke", "maze2", ("naive", "tp"), tmp_path)


def test_eta_auto_rows_compare_auto_variants_with_the_best_swept_ratio(maze2_runs):
    import eta_auto

    scale = common.SCALES["smoke"]
    floor = scale.config("maze2", "csac", etas=[("auto",)], normaliser="floor")
    _fake_run(maze2_runs / "maze2" / "csac_auto_floor", floor, {0: [1, 1, 1], 1: [0, 0, 1]})
    rows = eta_auto.domain_rows(maze2_runs, "maze2")
    # Intervals by hand: two seeds' resampled means span both; of three seeds (0, 0.5, 1 or 0, 0, 1), all three
    # equal has a chance of 1/27 > 2.5 %, so the interval reaches both ends.
    assert rows[0] == "| maze2 | best swept η = 0.1 | 0.33 [0.00, 0.67] | 0.33 [0.00, 0.67] | 0.67 0.00 | 400 (1/2 seeds) |"
    assert rows[1] == "| maze2 | auto, batch normaliser | 0.83 [0.67, 1.00] | 0.83 [0.67, 1.00] | 1.00 0.67 | 300 (2/2 seeds) |"
    assert rows[2] == "| maze2 | auto, floor normaliser | 0.67 [0.33, 1.00] | 0.67 [0.33, 1.00] | 1.00 0.33 | 400 (2/2 seeds) |"
    assert len(rows) == 3  # no ema run: no row
    # A call for another domain rewrites eta_auto.md with the maze2 rows kept.
    text = eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze3",), out=maze2_runs, table_only=True))
    assert rows[0] in text.splitlines() and (maze2_runs / "eta_auto.md").read_text() == text


def test_eta_auto_md_shows_the_eta_star_each_swept_run_logged(maze2_runs):
    """η* over the first third of the epochs (epoch 1: 0.8) → the last third (epoch 3: 0.6), per ratio trained."""
    import eta_auto

    text = eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2",), out=maze2_runs, table_only=True))
    lines = text.splitlines()
    assert lines[lines.index("## The paper's η* in the runs themselves") + 4:] == [
        "| domain | trained with η | agent 1 |", "|---|---|---|",
        "| maze2 | 0.1 | 0.80 → 0.60 |", "| maze2 | auto | 0.80 → 0.60 |"]
    assert "Over the last thirds it lies between 0.60 and 0.60." in text
    assert (maze2_runs / "eta_auto.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # the curves beside it


def test_ramp_rises_along_the_chain_and_is_trained_on_the_scales_and_the_fresh_seeds(maze2_runs, monkeypatch):
    import eta_auto

    assert eta_auto.ramp_etas(0.1, 0.5, "maze2") == (0.1,)  # one cooperative agent: LOW
    assert eta_auto.ramp_etas(0.1, 0.5, "maze3") == (0.1, 0.5)
    assert eta_auto.ramp_etas(0.1, 0.5, "maze4") == (0.1, 0.3, 0.5)
    calls = []
    monkeypatch.setattr(eta_auto, "run_grid", lambda config, out: calls.append((config, out)))
    eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze3",), normalisers=(), out=maze2_runs, sweep=False,
                                ramp=(0.1, 0.5)))
    [(config, out)] = calls
    assert out == maze2_runs / "maze3" / "csac_ramp" and config.grid.etas == ((0.1, 0.5),) and config.grid.seeds == (0, 1)
    calls.clear()
    eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2",), normalisers=(), out=maze2_runs, sweep=False,
                                ramp=(0.2, 0.5), fresh_seeds=2))
    (ramp, ramp_dir), (_, fresh_dir), (ramp_fresh, ramp_fresh_dir) = calls
    assert [ramp_dir.name, fresh_dir.name, ramp_fresh_dir.name] == ["csac_ramp", "csac_fresh_seeds",
                                                                     "csac_ramp_fresh_seeds"]
    assert ramp.grid.etas == ramp_fresh.grid.etas == ((0.2,),) and ramp_fresh.grid.seeds == (2, 3)
    _fake_run(ramp_dir, ramp, {0: [1, 1], 1: [0, 1]})
    _fake_run(ramp_fresh_dir, ramp_fresh, {0: [0, 0], 1: [0, 1]})
    rows = eta_auto.domain_rows(maze2_runs, "maze2")
    assert rows[-2:] == ["| maze2 | ramp η = 0.2 | 0.75 [0.50, 1.00] | 0.75 [0.50, 1.00] | 1.00 0.50 | 300 (2/2 seeds) |",
                         "| maze2 | ramp η = 0.2, fresh seeds 2–3 | 0.25 [0.00, 0.50] | 0.25 [0.00, 0.50] | 0.00 0.50 | 400 (1/2 seeds) |"]
    # The curves pool each variant over the scale's and the fresh seeds.
    groups = eta_auto.comparison_groups(maze2_runs, "maze2")
    assert {g[2]: len(series) for g, series in groups.items()} == {(0.1, 1.0): 2, ("auto", 1.0): 2, (0.2, 1.0): 4}
    calls.clear()
    with pytest.raises(SystemExit, match="^error: ramp: both ratios must lie in"):
        eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2",), out=maze2_runs, ramp=(0.1, 1.5)))
    assert calls == []  # refused before anything trained


@pytest.mark.parametrize("sweep", [True, False])
def test_eta_auto_trains_the_sweep_only_if_asked(tmp_path, monkeypatch, sweep):
    import eta_auto

    calls = []
    monkeypatch.setattr(eta_auto, "train_domain", lambda scale, domain, algos, out: calls.append(("sweep", domain)))
    monkeypatch.setattr(eta_auto, "run_grid", lambda config, out: calls.append((config.ablations.normaliser, out.name)))
    eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2",), normalisers=("floor",), out=tmp_path, sweep=sweep))
    assert calls == [("sweep", "maze2")] * sweep + [("floor", "csac_auto_floor")]


def test_fresh_seeds_train_the_best_ratio_and_auto_on_new_seeds_and_add_their_rows(maze2_runs, monkeypatch):
    """The ratio picked on seeds 0–1 (0.1) and auto, again on seeds 2–4; their rows come after the others."""
    import eta_auto

    calls = []
    monkeypatch.setattr(eta_auto, "run_grid", lambda config, out: calls.append((config, out)))
    eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2",), normalisers=(), out=maze2_runs, sweep=False,
                                fresh_seeds=3))
    [(config, out)] = calls
    assert out == maze2_runs / "maze2" / "csac_fresh_seeds"
    assert config.grid.etas == ((0.1,), ("auto",)) and config.grid.seeds == (2, 3, 4)
    _fake_run(out, config, {0: [1, 1], 1: [0, 0], 2: [0, 1], 3: [0, 0], 4: [0, 0], 5: [1, 1]})
    rows = eta_auto.domain_rows(maze2_runs, "maze2")
    assert rows[-2:] == ["| maze2 | best swept η = 0.1, fresh seeds 2–4 | 0.50 [0.00, 1.00] | 0.50 [0.00, 1.00] | 1.00 0.00 0.50 | 300 (2/3 seeds) |",
                         "| maze2 | auto, batch normaliser, fresh seeds 2–4 | 0.33 [0.00, 1.00] | 0.33 [0.00, 1.00] | 0.00 0.00 1.00 | 200 (1/3 seeds) |"]
    with pytest.raises(SystemExit, match="^error: fresh_seeds: must be >= 0"):
        eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2",), out=maze2_runs, fresh_seeds=-1))


def test_raw_sum_trains_none_at_eta_half_on_the_scales_and_the_fresh_seeds_and_adds_its_rows(maze2_runs, monkeypatch):
    import eta_auto

    calls = []
    monkeypatch.setattr(eta_auto, "run_grid", lambda config, out: calls.append((config, out)))
    eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2",), normalisers=(), out=maze2_runs, sweep=False,
                                raw_sum=True, fresh_seeds=3))
    (raw, raw_dir), (_, fresh_dir), (raw_fresh, raw_fresh_dir) = calls
    assert [raw_dir.name, fresh_dir.name, raw_fresh_dir.name] == ["csac_raw_sum", "csac_fresh_seeds",
                                                                   "csac_raw_sum_fresh_seeds"]
    for config, seeds in ((raw, (0, 1)), (raw_fresh, (2, 3, 4))):
        assert config.grid.etas == ((0.5,),) and config.ablations.normaliser == "none" and config.grid.seeds == seeds
    assert raw_fresh.differing(raw) == ["seeds"]  # the same experiment on other seeds
    _fake_run(raw_dir, raw, {0: [1, 1], 1: [0, 1]})
    _fake_run(raw_fresh_dir, raw_fresh, {0: [0, 0], 1: [0, 1], 2: [1, 1]})
    rows = eta_auto.domain_rows(maze2_runs, "maze2")
    assert rows[-2:] == ["| maze2 | raw sum (no normaliser, η = 0.5) | 0.75 [0.50, 1.00] | 0.75 [0.50, 1.00] | 1.00 0.50 | 300 (2/2 seeds) |",
                         "| maze2 | raw sum, fresh seeds 2–4 | 0.50 [0.00, 1.00] | 0.50 [0.00, 1.00] | 0.00 0.50 1.00 | 300 (2/3 seeds) |"]


def test_fresh_seeds_without_a_sweep_to_pick_from_fail_before_any_grid_trains(maze2_runs, monkeypatch):
    import eta_auto

    calls = []
    monkeypatch.setattr(eta_auto, "run_grid", lambda config, out: calls.append(out))
    with pytest.raises(SystemExit, match="^error: fresh_seeds: maze3 has no finished swept ratio") as err:
        eta_auto.main(eta_auto.Args(scale="smoke", domains=("maze2", "maze3"), normalisers=("floor",),
                                    out=maze2_runs, sweep=False, fresh_seeds=2))
    assert f"in {maze2_runs / 'maze3'} " in str(err.value)  # where it looked
    assert calls == []  # not even maze2's floor grid, which comes first


def test_default_results_folders_do_not_depend_on_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    expected = Path(common.__file__).resolve().parent / "results"
    assert common.results_folder(None, "table1", "cpu") == expected / "table1_cpu"
    assert common.results_folder(tmp_path / "x", "table1", "cpu") == tmp_path / "x"  # --out as given


def test_tp_primitives_are_the_naive_member_that_got_furthest():
    members = [dict(member=0, final_success=0.0, final_return=900.0),
               dict(member=1, final_success=0.3, final_return=500.0),
               dict(member=2, final_success=0.3, final_return=700.0)]
    assert table1.best_member(dict(members=members)) == 2  # success first, then return
    assert table1.best_member(dict(members=members[:1])) == 0


def test_table1_etas_narrow_the_csac_sweep_and_bad_ratios_name_the_field(tmp_path, monkeypatch):
    grids = []
    monkeypatch.setattr(table1, "run_grid", lambda config, folder, **_: grids.append((config, folder)))
    table1.train_domain("smoke", "maze4", ("csac", "sac"), tmp_path, etas=("0.9", "auto"))
    (csac, csac_dir), (sac, _) = grids
    assert csac.grid.etas == ((0.9,), ("auto",)) and csac_dir == tmp_path / "maze4" / "csac_etas_0.9-auto"
    assert sac.grid.etas == ((1.0,),)  # only CSAC sweeps ratios
    table1.train_domain("smoke", "maze4", ("csac",), tmp_path, etas=("0.1", "auto"))  # the scale's own set
    assert grids[-1][1] == tmp_path / "maze4" / "csac"
    # Without --etas, only the ratios no finished run holds for every seed are trained.
    scale = common.SCALES["smoke"]
    _fake_run(tmp_path / "maze3" / "csac_etas_0.1", scale.config("maze3", "csac", etas=[(0.1,)]), {0: [0], 1: [1]})
    table1.train_domain("smoke", "maze3", ("csac",), tmp_path)
    assert grids[-1][0].grid.etas == (("auto",),) and grids[-1][1] == tmp_path / "maze3" / "csac_etas_auto"
    _fake_run(grids[-1][1], grids[-1][0], {0: [0], 1: [1]})
    calls = len(grids)
    table1.train_domain("smoke", "maze3", ("csac",), tmp_path)
    assert len(grids) == calls  # all covered: nothing to train
    for bad, message in (("1.5", "^eta: ratios must be numbers in"), ("x", "^etas: cannot read 'x'")):
        with pytest.raises(ConfigError, match=message):
            table1.train_domain("smoke", "maze2", ("csac",), tmp_path, etas=(bad,))
    assert not (tmp_path / "maze2").exists()


def test_paper_projection_builds_table1s_grids_and_sums_the_sweeps():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments" / "bench"))
    import paper_projection as pp

    progs = dict(pp.programs(pp.Args(scale="paper", baselines=True), "maze4"))
    assert progs["csac grid"].grid_size == 10 * 5  # the nine paper ratios and auto, 5 seeds: table1.py's sweep
    assert progs["csac grid"].sac.hidden == (256, 256) and progs["csac grid"].num_agents == 4
    assert progs["csac single"].grid_size == 1
    assert progs["sac"].grid_size == progs["naive"].grid_size == 5
    assert progs["csac grid"].budget.total_steps // progs["csac grid"].budget.steps_per_epoch == 600
    assert [name for name, _ in pp.programs(pp.Args(scale="paper", grid=False), "peg")] == ["csac single"]

    def row(program, grid, epoch_s, projected_s):
        return dict(domain="maze4", program=program, grid=grid, agents=4, epoch_s=epoch_s,
                    per_run_epoch_s=epoch_s / grid, overhead_s=60.0, projected_s=projected_s, device="dev")

    text = pp.report([row("csac grid", 50, 10.0, 7200.0), row("csac single", 1, 2.0, 1800.0),
                      row("sac", 5, 1.0, 3600.0)])
    assert "| 0.100× |" in text  # per run 10 / 50 = 0.2 s against 2.0 s alone
    assert "3.00 h" in text  # the sweeps (csac grid + sac) only; the single run is a probe, not part of Table I
    with pytest.raises(SystemExit, match="domains"):
        pp.main(pp.Args(scale="paper", domains=("maze9",)))


def test_compare_pools_folders_per_variant_and_tests_each_row_against_the_first(tmp_path):
    scale = common.SCALES["smoke"]
    steps = scale.config("maze2", "csac").budget.steps_per_epoch
    a = scale.config("maze2", "csac", etas=[(0.1,)], seeds=2)
    _fake_run(tmp_path / "a", a, {0: [0, 1, 1], 1: [1, 1, 1]})
    _fake_run(tmp_path / "a2", scale.config("maze2", "csac", etas=[(0.1,)], seeds=2, first_seed=2),
              {0: [0, 0, 1], 1: [0, 1, 1]})
    b = scale.config("maze2", "csac", etas=[(0.1,), (0.9,)], seeds=2, normaliser="floor")
    _fake_run(tmp_path / "b", b, {0: [0, 0, 0], 1: [0, 0, 0], 2: [0, 0, 1], 3: [0, 0, 0]})
    text = compare.main(compare.Args(variants=(f"A={tmp_path / 'a'},{tmp_path / 'a2'}", f"B={tmp_path / 'b'}"),
                                     at=(steps, 3 * steps), out=tmp_path / "t.md"))
    lines = text.splitlines()
    # A pools seeds 0-3: successes at epoch 1 (0 1 0 0) and 3 (1 1 1 1); finals 2/3, 1, 1/3, 2/3.
    assert lines[2] == "| A | 4 | 0.25 / 1.00 | 0.67 ± 0.24 | 3 of 4 |  |"
    assert lines[3].startswith("| B, csac η=0.1 | 2 | 0.00 / 0.00 | 0.00 ± 0.00 | 0 of 2 | 0.")
    assert lines[4].startswith("| B, csac η=0.9 | 2 | 0.00 / 0.50 | 0.17 ± 0.17 | 0 of 2 | 0.")
    assert "A: 0.67 1.00 0.33 0.67" in lines[-1] and (tmp_path / "t.md").read_text() == text
    # Chance that 2 seeds reach 0.5 at epoch 1 and 1.0 at epoch 3: the 3 of A's 6 pairs that hold seed 1;
    # B has 2 seeds, so 1 pair per ratio: (0, 0) at epoch 1 misses.
    text = compare.main(compare.Args(variants=(f"A={tmp_path / 'a'},{tmp_path / 'a2'}", f"B={tmp_path / 'b'}"),
                                     at=(steps, 3 * steps), reference=(0.5, 1.0), draw=2))
    lines = text.splitlines()
    assert lines[0].endswith("| 2 seeds reach 0.5 / 1 |") and lines[1] == "|---" * 7 + "|"
    assert lines[2].endswith("| 3 of 4 |  | 0.500 |") and lines[3].endswith(" 0.000 |")
    text = compare.main(compare.Args(variants=(f"A={tmp_path / 'a'}",), at=(steps, 3 * steps), reference=(0, 0), draw=3))
    assert text.splitlines()[2].endswith("| – |")  # 2 seeds cannot make a 3-seed study
    with pytest.raises(SystemExit, match="^error: reference: one value per --at step"):
        compare.Args(variants=("A=x",), at=(steps,), reference=(0.1, 0.2))
    with pytest.raises(SystemExit, match="^error: variants: expected LABEL=DIR"):
        compare.main(compare.Args(variants=(str(tmp_path / "a"),)))
    with pytest.raises(SystemExit, match="holds no run"):
        compare.main(compare.Args(variants=(f"C={tmp_path / 'missing'}",)))


def test_compare_reads_a_run_still_training_from_its_metrics_so_far(tmp_path):
    """No summary.json yet and a last row half written: the rows logged so far count, and the table says so."""
    scale = common.SCALES["smoke"]
    steps = scale.config("maze2", "csac").budget.steps_per_epoch
    config = scale.config("maze2", "csac", etas=[(0.1,)], seeds=2, total_steps=10 * steps)
    _fake_run(tmp_path / "r", config, {0: [0, 1, 1], 1: [0, 0, 1]})
    (tmp_path / "r" / "summary.json").unlink()
    with (tmp_path / "r" / "metrics.jsonl").open("a") as f:
        f.write('{"member": 0, "epoch": 4, "succ')  # the trainer is writing epoch 4
    text = compare.main(compare.Args(variants=(f"R={tmp_path / 'r'}",), at=(steps, 3 * steps, 4 * steps)))
    lines = text.splitlines()
    assert lines[2] == "| R | 2 | 0.00 / 1.00 / – | 0.50 ± 0.17 | 1 of 2 |  |"  # finals 2/3 and 1/3
    assert lines[-1].endswith(f"{tmp_path / 'r'}: {3 * steps:,} of {10 * steps:,} env steps")


def test_scripts_end_bad_input_in_one_line_naming_the_field(tmp_path, monkeypatch, capsys):
    """common.cli turns the script's bad-input errors into `error: FIELD: ...` (no traceback); others propagate."""
    def bad(args):
        raise ConfigError("seeds", "at least one seed")

    monkeypatch.setattr(sys, "argv", ["table1.py"])
    with pytest.raises(SystemExit, match="^error: seeds: at least one seed$"):
        common.cli(bad, table1.Args)
    with pytest.raises(ZeroDivisionError):
        common.cli(lambda args: 1 / 0, table1.Args)
    # End to end: compare.py asked to pool two different experiments names the differing field.
    scale = common.SCALES["smoke"]
    _fake_run(tmp_path / "a", scale.config("maze2", "csac"), {0: [0], 1: [1]})
    _fake_run(tmp_path / "b", scale.config("maze2", "csac", normaliser="floor"), {0: [1], 1: [1]})
    script = Path(__file__).resolve().parents[1] / "experiments" / "compare.py"
    done = subprocess.run([sys.executable, str(script), f"X={tmp_path / 'a'},{tmp_path / 'b'}"],
                          capture_output=True, text=True)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.startswith("error: ") and "differ in normaliser" in done.stderr


def test_scripts_split_the_cpu_for_the_largest_grid_they_train(monkeypatch):
    """Each training script names its largest grid (ratios x seeds, by hand from its scale or plan), and
    common.cli splits the CPU for it before main runs; a call that trains nothing names none."""
    import eta_auto

    def parse(script: str, *argv: str):
        monkeypatch.setattr(sys, "argv", [script, *argv])
        return common.tyro.cli(sys.modules[script.removesuffix(".py")].Args)

    # table1 at the cpu scale: 6 ratios (5 numbers and auto) x 3 seeds; a subset; baselines only: the seeds.
    assert table1.largest_grid(parse("table1.py")) == 18
    assert table1.largest_grid(parse("table1.py", "--etas", "0.9", "auto")) == 6
    assert table1.largest_grid(parse("table1.py", "--algos", "sac", "naive")) == 3
    assert table1.largest_grid(parse("table1.py", "--table-only")) is None
    # eta_auto: the sweep, or the best ratio and auto on the fresh seeds, or one ratio on the scale's seeds.
    assert eta_auto.largest_grid(parse("eta_auto.py")) == 18
    assert eta_auto.largest_grid(parse("eta_auto.py", "--no-sweep", "--fresh-seeds", "12")) == 24
    assert eta_auto.largest_grid(parse("eta_auto.py", "--no-sweep")) == 3
    # paper_budget: one cell's seeds (5), or a chunk of them; a report trains nothing.
    assert paper_budget.largest_grid(parse("paper_budget.py")) == 5
    assert paper_budget.largest_grid(parse("paper_budget.py", "--seeds-per-grid", "3")) == 3
    assert paper_budget.largest_grid(parse("paper_budget.py", "--cells", "maze4/csac_ramp", "maze4/sac")) == 5
    assert paper_budget.largest_grid(parse("paper_budget.py", "--report-only")) is None
    # independent_ratios: 3 x 3 pairs x 3 seeds, or the pairs asked for.
    assert independent_ratios.largest_grid(parse("independent_ratios.py")) == 27
    assert independent_ratios.largest_grid(parse("independent_ratios.py", "--pairs", "0.1,1.0", "1.0,0.1")) == 6
    # cli splits before main, with the script's count.
    calls = []
    monkeypatch.setattr(common, "split_host_cpu", lambda devices, grid=None: calls.append((devices, grid)))
    monkeypatch.setattr(sys, "argv", ["table1.py", "--etas", "0.9", "auto"])
    common.cli(lambda args: calls.append("main"), table1.Args, largest_grid=table1.largest_grid)
    common.cli(lambda args: calls.append("main"), table1.Args)
    assert calls == [("auto", 6), "main", ("auto", None), "main"]
    # Bad pairs end in one line naming the field, before anything is split.
    monkeypatch.setattr(sys, "argv", ["independent_ratios.py", "--pairs", "0.1"])
    with pytest.raises(SystemExit, match="^error: pairs: "):
        common.cli(lambda args: None, independent_ratios.Args, largest_grid=independent_ratios.largest_grid)
    assert len(calls) == 4


def test_vs_prototype_reports_times_against_the_prototype_and_scaled_to_spec_roof():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments" / "bench"))
    import vs_prototype as vp

    assert vp.scaled(3.0, 74.0) == pytest.approx(1.5)  # half the prototype machine's roof: twice as fast there
    text = vp.report([dict(name="3 rooms, one run", devices=1, epochs=[2.0, 3.0, 9.0], roofs=[74.0, 74.0]),
                      dict(name="2 rooms, grid of 3, one device", devices=1, epochs=[6.0], roofs=[148.0, 148.0])])
    # median 3.0 s against 2.5 s: 1.20; at the prototype machine's roof 1.50 s, 0.60 of the prototype's
    assert "| 3 rooms, one run | one run | 1 | 3.00 (2.00–9.00) | 74 | 2.5 | 1.20 | 1.50 | 0.60 |" in text
    assert "| 2 rooms, grid of 3 | one device, vmapped | 1 | 6.00 (6.00–6.00) | 148 | 4.0 | 1.50 | 6.00 | 1.50 |" in text
    assert {c.figure for c in vp.CONFIGS.values()} == {"3 rooms, one run", "2 rooms, grid of 3"}  # both of the prototype's


def test_vs_rejax_reports_the_median_of_paired_ratios_per_grid():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments" / "bench"))
    import vs_rejax  # rejax itself is imported only when a RejaxRun is built

    prog = lambda times, compile_s=1.0: {"times": times, "compile_s": compile_s}
    row = {"grid": 4, "programs": {"rejax_no_eval": prog([2.0, 3.0, 9.0], 18.0), "rejax": prog([2.0, 2.0, 2.0]),
                                   "ours_no_eval": prog([1.0, 1.0, 1.0], 10.0), "ours": prog([4.0, 1.0, 1.0]),
                                   "rejax_uniform": prog([1.0, 1.5, 0.5])}}
    text = vs_rejax.report([row], vs_rejax.Args())
    # same work: 2, 3, 9 -> 3; with evaluation 0.5, 2, 2 -> 2; rejax with our sampler / ours 1, 1.5, 0.5 -> 1
    assert "| 4 | ours | 1.00 | 3.00 (2.00–9.00) | 1.00 | 10.0 |" in text
    assert "| 4 | ours, with its evaluation | 1.00 | 2.00 (0.50–2.00) |  | 1.0 |" in text
    assert "| 4 | rejax SAC | 3.00 | 1.00 (1.00–1.00) | 0.50 | 18.0 |" in text
    assert "ours, members one at a time" not in text  # only the programs that ran
    assert "5000 env steps and 1000 updates per seed" in text


def test_auto_variants_figure_pools_each_domains_seeds_per_line_from_the_committed_runs():
    import auto_variants

    for domain, (_, _, variants) in auto_variants.PANELS.items():
        groups = auto_variants.panel(domain)
        assert [legend for _, legend, _ in groups] == [legend for legend, _, _ in variants], domain
        seeds = 3 if domain == "peg" else 6
        assert all(len(series) == seeds for series in groups.values()), domain


def test_ratio_seeds_reads_table_1s_3_room_finals_back_from_the_committed_runs(tmp_path):
    """The η filter and the 300 k cut reproduce Table I's published 3-room cells (η = 0.1: 0.00 on seeds 0-2;
    η = 0.3: 1.00 0.93 1.00), leave out the grid's other ratios and `auto`, and a 3 M-step run is cut at 300 k."""
    import ratio_seeds
    from ccp_jax import outputs

    results = common.RESULTS
    low, _ = ratio_seeds.scores(results / "table1_cpu_forward_slide/maze3/csac", 0.1, 300_000)
    high, _ = ratio_seeds.scores(results / "table1_cpu_forward_slide/maze3/csac", 0.3, 300_000)
    assert low == {0: 0.0, 1: 0.0, 2: 0.0}
    assert [round(v, 2) for v in high.values()] == [1.0, 0.93, 1.0]
    long_run = results / "paper_budget/maze3/csac_0.3"
    cut, held = ratio_seeds.scores(long_run, 0.3, 300_000)
    rows = [r for r in outputs.read_rows(outputs.metrics_file(long_run)) if r["seed"] == 30]
    window = sorted((r["env_steps"], r["success_rate"]) for r in rows if r["env_steps"] <= 300_000)[-10:]
    assert window[-1][0] == 300_000 and cut[30] == pytest.approx(np.mean([s for _, s in window]))
    assert 0 < held <= 1_000_000
    assert ratio_seeds.scores(tmp_path, 0.1, 300_000) is None  # not committed (yet)


def test_ratio_seeds_tells_the_4_room_ramp_from_a_shared_ratio_and_reads_split_cells(tmp_path):
    """On 4 rooms, seeds 0-11 at 400 k, the per-agent ramp solves 6 of 12 (mean 0.49) and η = 0.5 2 of 12, as
    results.md publishes; a grid training auto, 0.5 and the ramp side by side gives each its own members; a
    paper-budget cell split into seed chunks is read from every committed chunk."""
    import ratio_seeds

    base = common.RESULTS / "table1_cpu_forward_slide/maze4"

    def finals(eta, names):
        return [v for n in names for v in ratio_seeds.scores(base / n, eta, 400_000)[0].values()]
    shared = finals(0.5, ["csac_etas_0.5-0.7", "csac_fresh_seeds", "csac_ramp_and_0.5_seeds6to8",
                          "csac_trusted_0.5_ramp_seeds9to11"])
    ramp = finals(ratio_seeds.RAMP, ["csac_ramp", "csac_ramp_fresh_seeds", "csac_ramp_and_0.5_seeds6to8",
                                     "csac_trusted_0.5_ramp_seeds9to11"])
    assert len(shared) == len(ramp) == 12
    assert sum(v >= 0.5 for v in ramp) == 6 and round(float(np.mean(ramp)), 2) == 0.49
    assert sum(v >= 0.5 for v in shared) == 2
    mixed = base / "csac_trusted_0.5_ramp_seeds9to11"
    assert set(ratio_seeds.scores(mixed, ratio_seeds.RAMP, 400_000)[0]) == {9, 10, 11}
    for chunk in ("csac_0.1_seeds30to31", "csac_0.1_seeds32to33", "csac_0.1_seeds34to34"):
        (tmp_path / "maze3" / chunk).mkdir(parents=True)
    for chunk in ("csac_0.1_seeds30to31", "csac_0.1_seeds34to34"):  # 32-33 still training: not read
        (tmp_path / "maze3" / chunk / "summary.json").write_text("{}")
    assert [p.name for p in ratio_seeds.folders(tmp_path, "maze3/csac_0.1")] == ["csac_0.1_seeds30to31",
                                                                                 "csac_0.1_seeds34to34"]
    assert ratio_seeds.folders(tmp_path, "maze3/csac_0.3") == []


def _fake_pbt_compare_block(out: Path, args, block: int, arm: str, success: dict[int, float],
                            fitness: dict[int, float]) -> None:
    """One finished grid of pbt_compare with given final eval success and training fitness per member (2 stages:
    fitness = (reached stage 1 + succeeded) / 2; every training episode that reaches stage 1 here succeeds)."""
    from ccp_jax import outputs

    config = pbt_compare.grid_config(args, "maze2", block, arm)
    folder = pbt_compare.folder(out, "maze2", block, arm)
    folder.mkdir(parents=True)
    outputs.write_json(folder / "config.json", config.to_dict())
    rows = [dict(member=m, seed=seed, eta=list(eta), algo="csac", epoch=epoch, env_steps=epoch * 200,
                 success_rate=success[m], eval_return=success[m], stage_reached_mean=success[m],
                 train_episodes=4.0, train_success=fitness[m], train_stage_fraction=[1.0, fitness[m]])
            for m, (eta, seed) in enumerate(config.members) for epoch in (1, 2)]
    outputs.write_rows(folder / "metrics.jsonl", rows)
    outputs.write_json(folder / "summary.json", outputs.summarise(config, rows, wall_s=2.0))


def test_pbt_compare_keeps_the_fittest_member_and_scores_the_sweeps_pick_on_the_other_blocks(tmp_path):
    parents = lambda *p: [dict(pbt_parent=x) for x in p]
    # epoch 1: 1 copies 0; epoch 2: 2 copies 1, which by then carries 0's line
    assert pbt_compare.carried_lines({0: parents(-1, -1), 1: parents(0, -1), 2: parents(-1, 1)}) == {0: 0, 1: 0, 2: 0}
    # copies at one ranking read the states before it: 2 gets the line 1 had, not the one 1 takes then
    assert pbt_compare.carried_lines({0: parents(-1), 1: parents(0), 2: parents(1)}) == {0: 0, 1: 0, 2: 1}
    # scored on the epochs since its last copy (the donor's line): 0.0 before, 1.0 after the copy at epoch 2
    rows = [dict(success_rate=0.0, pbt_parent=-1), dict(success_rate=0.0, pbt_parent=3)] + [dict(success_rate=1.0)] * 2
    assert pbt_compare.final_success(rows) == 1.0
    assert pbt_compare.final_success([dict(success_rate=v) for v in (0.0, 0.5, 1.0)]) == 0.5  # a sweep: all of them
    assert pbt_compare.training_fitness([dict(train_episodes=4.0, train_success=0.25,
                                              train_stage_fraction=[1.0, 0.5])], window=1) == pytest.approx(0.375)
    args = pbt_compare.Args(scale="smoke", blocks=2, etas=(0.1, 0.5), seeds_per_block=1, out=tmp_path)
    # members: (0.1, seed), (0.5, seed). Block 0: 0.5 evaluates best but 0.1 trains fitter, so 0.1 is kept.
    _fake_pbt_compare_block(tmp_path, args, 0, "sweep", {0: 0.2, 1: 0.9}, {0: 0.8, 1: 0.1})
    _fake_pbt_compare_block(tmp_path, args, 0, "pbt", {0: 0.6, 1: 0.0}, {0: 0.9, 1: 0.0})
    _fake_pbt_compare_block(tmp_path, args, 1, "sweep", {0: 0.4, 1: 0.3}, {0: 0.1, 1: 0.7})
    _fake_pbt_compare_block(tmp_path, args, 1, "pbt", {0: 1.0, 1: 0.5}, {0: 0.6, 1: 0.5})
    sweeps = [pbt_compare.grid_scores(pbt_compare.folder(tmp_path, "maze2", b, "sweep"), 2) for b in (0, 1)]
    assert [g["best"]["success"] for g in sweeps] == [0.2, 0.3]  # by training fitness, not by evaluation
    # block 0 picks 0.5 (0.9), scored on block 1's 0.5 member (0.3); block 1 picks 0.1 (0.4), scored on block 0's (0.2)
    assert pbt_compare.sweep_pick_on_fresh_seeds(sweeps) == [(0.5, pytest.approx(0.3)), (0.1, pytest.approx(0.2))]
    text = pbt_compare.report(args, tmp_path, "maze2")
    assert "| population | best | 0.80 [" in text and "| 0.60 1.00 |" in text
    assert "| sweep's pick, on the other blocks' seeds | η = 0.5, 0.1 | 0.25 [" in text
    assert "auto" not in text
    # a grid of auto members has no starting ratio to pick: it is kept by fitness alone and read beside the others
    args = pbt_compare.Args(scale="smoke", blocks=2, etas=(0.1, 0.5), seeds_per_block=1, out=tmp_path,
                            auto_rule="trusted")
    _fake_pbt_compare_block(tmp_path, args, 0, "trusted", {0: 0.0, 1: 0.7}, {0: 0.2, 1: 0.3})
    _fake_pbt_compare_block(tmp_path, args, 1, "trusted", {0: 0.1, 1: 0.5}, {0: 0.4, 1: 0.3})
    autos = pbt_compare.grid_scores(pbt_compare.folder(tmp_path, "maze2", 0, "trusted"), 2)
    assert autos["picked_eta"] is None and autos["best"]["success"] == 0.7
    text = pbt_compare.report(args, tmp_path, "maze2")
    assert "| auto, trusted (2 blocks) | best | 0.40 [" in text and "| 0.70 0.10 |" in text
    assert "P(population's kept member > auto's kept member), over all pairs of blocks: 0.75 [" in text


def _fake_peg_sweep(folder: Path, finals: dict[float, tuple[float, float, float]]) -> None:
    """A finished peg_budget sweep: every member of ratio eta ends with (success, hand-over, thick-section grasps)."""
    from ccp_jax import outputs

    config = peg_budget.SWEEP.config(smoke=True)
    folder.mkdir(parents=True)
    outputs.write_json(folder / "config.json", config.to_dict())
    rows = [dict(member=m, seed=seed, eta=list(eta), algo="csac", epoch=1, env_steps=200,
                 success_rate=finals[eta[0]][0], eval_return=0.0, stage_reached_mean=finals[eta[0]][1],
                 stage_fraction=[1.0, finals[eta[0]][1]],
                 eval_end={"grasp_thick": finals[eta[0]][2], "grasp_thin": finals[eta[0]][1] - finals[eta[0]][2]})
            for m, (eta, seed) in enumerate(config.members)]
    outputs.write_rows(folder / "metrics.jsonl", rows)
    outputs.write_json(folder / "summary.json", outputs.summarise(config, rows, wall_s=1.0))


def test_peg_sweep_picks_by_success_then_thick_grasps_then_handovers(tmp_path):
    assert peg_budget.best_swept_eta(tmp_path / "missing") is None  # not finished: no pick
    base = {0.1: (0.0, 0.9, 0.1), 0.3: (0.0, 0.5, 0.4), 0.5: (0.0, 1.0, 0.0), 0.7: (0.0, 0.2, 0.2), 0.9: (0.0, 0.8, 0.4)}
    _fake_peg_sweep(tmp_path / "a", base)  # nothing inserts: the most thick-section grasps, ties by hand-over
    assert peg_budget.best_swept_eta(tmp_path / "a") == 0.9
    _fake_peg_sweep(tmp_path / "b", {**base, 0.1: (0.1, 0.9, 0.1)})  # any insertion wins
    assert peg_budget.best_swept_eta(tmp_path / "b") == 0.1
    _fake_peg_sweep(tmp_path / "out" / "sweep", base)
    assert peg_budget.best_cell(tmp_path / "out") is None  # 0.9: trained anyway as csac_0.9
    _fake_peg_sweep(tmp_path / "out2" / "sweep", {**base, 0.3: (0.2, 0.5, 0.4)})
    assert peg_budget.best_cell(tmp_path / "out2") == peg_budget.Cell("csac_0.3", "csac", ((0.3,),))


def test_peg_held_cells_train_the_grip_held_variant_and_say_so():
    assert [c.config(smoke=True).ablations.peg_grip_held for c in peg_budget.QUEUE + peg_budget.HELD] == \
        [False] * len(peg_budget.QUEUE) + [True] * len(peg_budget.HELD)
    assert [peg_budget.label(c.name) for c in peg_budget.HELD] == ["CSAC η = 0.9, grip held", "Naive, grip held"]


def test_peg_final_evaluation_is_read_back_and_tabled_per_seed(tmp_path):
    """final_eval.json rows become one table row per cell; an unfinished grid has no final evaluation, and a
    finished one that already has its file is read, not evaluated again (its checkpoints are left alone)."""
    from ccp_jax import outputs

    assert peg_budget.final_evaluation(tmp_path / "missing") is None
    _fake_peg_sweep(tmp_path / "sweep", {eta: (0.0, 0.5, 0.0) for eta in (0.1, 0.3, 0.5, 0.7, 0.9)})
    (tmp_path / "sweep" / "summary.json").unlink()
    (tmp_path / "sweep" / "checkpoints").mkdir()
    assert peg_budget.final_evaluation(tmp_path / "sweep") is None  # still training
    rows = [dict(member=m, seed=30 + m, eta=[0.9, 1.0], episodes=50, stochastic=False, success_rate=s,
                 stage_fraction=[1.0, h], eval_end={"grasp_thick": 0.0, "grasp_thin": h, "hold_thick": s})
            for m, (s, h) in enumerate([(0.82, 0.96), (0.0, 1.0), (0.0, 0.94)])]
    outputs.write_json(tmp_path / "sweep" / peg_budget.FINAL_EVAL, rows)
    assert peg_budget.final_evaluation(tmp_path / "sweep") == rows
    assert (tmp_path / "sweep" / "checkpoints").is_dir()
    lines = peg_budget.final_table({"csac_0.9": rows})
    assert "50 deterministic episodes per seed" in lines[1]
    assert lines[-1] == "| CSAC η = 0.9 | 30 31 32 | 0.82 0.00 0.00 | 0.96 1.00 0.94 | 0.96 1.00 0.94 | 0.82 0.00 0.00 |"
    assert peg_budget.final_table({}) == []
