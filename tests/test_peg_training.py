"""Every algorithm trains on the peg-in-hole task (one tiny epoch each), on both robot models and both physics;
a run on the C physics resumes bit for bit."""
import json

import jax
import numpy as np
import pytest

from ccp_jax import checkpoint
from ccp_jax.config import Config
from ccp_jax.envs import make_env
from ccp_jax.grid import make_grid_train
from ccp_jax.train import main

TINY = ["--preset", "tiny", "--steps-per-epoch", "40", "--max-episode-steps", "20", "--eval-episodes", "2",
        "--train-loops-per-epoch", "5", "--batch-size", "8", "--no-progress", "--no-tensorboard"]


@pytest.mark.parametrize("algo,model,physics", [
    ("csac", "arm", "mjx"), pytest.param("naive", "arm", "mjx", marks=pytest.mark.slow),
    pytest.param("sac", "arm", "mjx", marks=pytest.mark.slow),
    pytest.param("csac", "hand", "mjx", marks=pytest.mark.slow), ("csac", "hand", "c"),
    pytest.param("sac", "arm", "c", marks=pytest.mark.slow)])
def test_one_epoch_on_peg(tmp_path, algo, model, physics):
    summary = main(["--env", "peg", "--peg-model", model, "--peg-physics", physics, "--algo", algo,
                    "--total-steps", "40", "--out", str(tmp_path / algo)] + TINY)
    task = json.loads((tmp_path / algo / "config.json").read_text())["task"]
    assert (task["peg_model"], task["peg_physics"]) == (model, physics)
    member = summary["members"][0]
    assert member["algo"] == algo and member["env_steps"] == 40 and member["epochs"] == 1
    assert 0.0 <= member["final_success"] <= 1.0


def _final(run_dir):
    """(metrics rows without wall times, the last checkpoint's state) of a run."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    for r in rows:
        r.pop("epoch_wall_s")
    config = Config.from_dict(json.loads((run_dir / "config.json").read_text()))
    trainer = make_grid_train(config, make_env(config))
    mngr = checkpoint.manager(run_dir)
    _, state = checkpoint.restore(mngr, trainer.abstract_state(config.grid_arrays()[1]))
    mngr.close()
    return rows, jax.device_get(state)


def test_c_physics_run_resumes_bit_for_bit(tmp_path):
    """Two epochs straight, against one epoch and a resume that raises the budget to two: the same metrics and
    the same final state, the env's carried C MuJoCo state included."""
    args = ["--env", "peg", "--peg-model", "hand", "--peg-physics", "c", "--checkpoint-every", "1"] + TINY
    main(args + ["--total-steps", "80", "--out", str(tmp_path / "full")])
    main(args + ["--total-steps", "40", "--out", str(tmp_path / "split")])
    main(["--resume", str(tmp_path / "split"), "--total-steps", "80", "--no-progress"])
    (rows_a, a), (rows_b, b) = _final(tmp_path / "full"), _final(tmp_path / "split")
    assert rows_a == rows_b and len(rows_a) == 2
    assert a.env_state.pipeline_state.state.dtype == np.uint32
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


def test_critic_probe_and_the_final_evaluation_of_a_grip_held_run(tmp_path):
    """experiments/peg_critic_probe.py on a one-epoch grip-held run: the scripted hand-overs land where they
    should (thick section behind the centre, centre grasp at it) and every member gets finite critic values; then
    peg_budget's final evaluation writes its files, tables the probe and deletes the checkpoints."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
    import peg_budget
    import peg_critic_probe

    args = list(TINY)
    args[args.index("--max-episode-steps") + 1] = "200"  # long enough for a scripted grasp to hand over
    main(["--env", "peg", "--peg-model", "hand", "--peg-physics", "c", "--peg-grip-held", "True",
          "--eta", "0.9", "--seeds", "2", "--total-steps", "40", "--checkpoint-every", "1",
          "--out", str(tmp_path / "run")] + args)
    result = peg_critic_probe.probe(tmp_path / "run", epoch=None, starts=1, seed=3)
    assert np.mean(result["offset"]["thick"]) < -0.03 and abs(np.mean(result["offset"]["centre"])) < 0.01
    assert [r["seed"] for r in result["members"]] == [0, 1]
    for r in result["members"]:
        values = [r[g][k] for g in peg_critic_probe.GRASPS for k in ("q1", "q2", "v2_after")]
        assert np.isfinite(values).all() and r["norm_range_next"] > 0
        assert all(r[g]["inserts"] in (0.0, 1.0) for g in peg_critic_probe.GRASPS)
        if "decision" in r:  # the untrained first agent closed the gripper somewhere before a hand-over
            assert r["decision"]["closes"] == 1 and np.isfinite(r["decision"]["gain_c"])  # CSAC: its objective
    assert "| 1 | 1 | 0.9,1 | centre |" in peg_critic_probe.table(result)

    run = tmp_path / "run"
    rows = peg_budget.final_evaluation(run, episodes=2, probe_starts=1)
    assert [r["episodes"] for r in rows] == [2, 2] and not (run / "checkpoints").exists()
    noisy = json.loads((run / peg_budget.STOCHASTIC_EVAL).read_text())
    assert [r["stochastic"] for r in noisy] == [True, True]
    probe = json.loads((run / peg_budget.CRITIC_PROBE).read_text())
    assert probe["run"] == "run" and probe["epoch"] == 1 and probe["seed"] == peg_budget.PROBE_SEED
    line = peg_budget.probe_table({"csac_0.9_held": (probe, noisy)})[-1]
    assert line.startswith("| CSAC η = 0.9, grip held | 1 | 0 1 | ")
    naive = dict(closes=1, grip_from_centre=0.08, gain_q1=-0.3, gain_q2=0.0, gain_c=None, balance_eta=None)
    probe["members"] = [{**m, "decision": naive} for m in probe["members"]]  # no cooperative objective
    thick = " ".join(f"{r['eval_end']['grasp_thick']:.2f}" for r in noisy)
    assert peg_budget.probe_table({"naive_held": (probe, noisy)})[-1].endswith(
        f"| +0.080 +0.080 | -0.30 -0.30 | – – | {thick} |")
    assert "| – | – |" in peg_critic_probe.table(probe)
    assert sorted(p.name for p in (run / "policies").iterdir())[:2] == ["member0.jaxexport", "member0.json"]
