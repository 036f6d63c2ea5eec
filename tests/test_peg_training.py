"""Every algorithm trains on the MJX peg-in-hole task (one tiny epoch each), on both robot models."""
import json

import pytest

from ccp_jax.train import main


@pytest.mark.parametrize("algo,model", [("csac", "arm"), pytest.param("naive", "arm", marks=pytest.mark.slow),
                                        pytest.param("sac", "arm", marks=pytest.mark.slow),
                                        pytest.param("csac", "hand", marks=pytest.mark.slow)])
def test_one_epoch_on_peg(tmp_path, algo, model):
    summary = main(["--env", "peg", "--peg-model", model, "--algo", algo, "--preset", "tiny",
                    "--steps-per-epoch", "40", "--total-steps", "40", "--max-episode-steps", "20",
                    "--eval-episodes", "2",
                    "--train-loops-per-epoch", "5", "--batch-size", "8", "--out", str(tmp_path / algo),
                    "--no-progress", "--no-tensorboard"])
    assert json.loads((tmp_path / algo / "config.json").read_text())["task"]["peg_model"] == model
    member = summary["members"][0]
    assert member["algo"] == algo and member["env_steps"] == 40 and member["epochs"] == 1
    assert 0.0 <= member["final_success"] <= 1.0
