"""python -m ccp_jax.export: the stage chain as one jax.export artefact, run in a fresh process with jax alone."""
import json
import subprocess
import sys

import jax
import numpy as np
import pytest

from ccp_jax import export
from ccp_jax.config import make_config
from ccp_jax.envs import make_env
from ccp_jax.policy import load_policy
from ccp_jax.train import run

_RUN_IN_FRESH_PROCESS = """
import sys, jax, numpy as np
data = np.load(sys.argv[2])
policy = jax.export.deserialize(bytearray(open(sys.argv[1], "rb").read()))
actions = [np.asarray(policy.call(data["obs"], np.full(len(data["obs"]), s, np.int32))) for s in range(3)]
one = np.asarray(policy.call(data["obs"][:1], np.zeros(1, np.int32)))  # the batch size is symbolic
assert not any(m.startswith(("ccp_jax", "envs_mjx", "flax")) for m in sys.modules), "needs more than jax"
np.savez(sys.argv[3], actions=np.stack(actions), one=one)
"""


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished tiny 3-room CSAC grid of 2 seeds and observations the envs produced."""
    out = tmp_path_factory.mktemp("export") / "run"
    config = make_config("tiny", rooms=3, seeds=(0, 1))
    run(config, out, progress=False, tensorboard=False)
    env = make_env(config)
    states = jax.vmap(env.reset)(jax.random.split(jax.random.key(7), 9))
    states = jax.vmap(env.step)(states, jax.random.uniform(jax.random.key(8), (9, env.action_size), minval=-1))
    return out, np.asarray(states.obs, np.float32)


def test_the_artefact_matches_the_policy_per_stage_in_a_process_without_ccp_jax(trained, tmp_path):
    out, obs = trained
    path = export.main([str(out), "--member", "1", "--out", str(tmp_path / "chain.jaxexport")])
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["member"] == 1 and meta["seed"] == 1 and meta["num_stages"] == 3 and meta["obs_size"] == obs.shape[1]
    assert "cpu" in meta["platforms"]
    np.savez(tmp_path / "obs.npz", obs=obs)
    done = subprocess.run([sys.executable, "-c", _RUN_IN_FRESH_PROCESS, str(path), str(tmp_path / "obs.npz"),
                           str(tmp_path / "actions.npz")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    got = np.load(tmp_path / "actions.npz")
    policy = load_policy(out, member=1)
    for stage in range(3):
        want = np.asarray(policy(obs, np.full(len(obs), stage, np.int32)))
        np.testing.assert_allclose(got["actions"][stage], want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got["one"], got["actions"][0][:1], rtol=1e-6, atol=1e-7)
    # Each stage's agent acts differently: the stage really selects the agent.
    assert not np.allclose(got["actions"][0], got["actions"][1])


def test_members_differ_and_bad_input_is_refused(trained, tmp_path):
    out, obs = trained
    chains = [export.export_chain(out, member=m)[0] for m in (0, 1)]
    stage = np.zeros(len(obs), np.int32)
    assert not np.allclose(chains[0].call(obs, stage), chains[1].call(obs, stage))
    with pytest.raises(SystemExit, match="member"):
        export.main([str(out), "--member", "2"])
    with pytest.raises(SystemExit, match="run_dir"):
        export.main([str(tmp_path / "nothing")])
