"""Population-based training of η: selection, copy and perturbation by hand, then runs from the CLI (lineage,
resume bit for bit). The sharded grid is in test_multidevice.py."""
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccp_jax import outputs, plot
from ccp_jax.collect import EpisodeStats
from ccp_jax.config import ConfigError, make_config
from ccp_jax.pbt import PbtMember, exploit_explore, fitness, pbt_step, perturb, select
from ccp_jax.train import main, run
from ccp_jax.trainer import TrainState
from saved import latest_state  # tests/ is on sys.path (conftest)

# 4 members, 3 epochs, a ranking after every epoch: one member replaced each time (⌊0.25 × 4⌋).
CONFIG = make_config("tiny", etas=((0.1,), (0.9,)), seeds=(0, 1), pbt_every=1, total_steps=600)
CLI = ["--preset", "tiny", "--eta", "0.1", "0.9", "--seeds", "2", "--pbt-every", "1", "--total-steps", "600",
       "--no-progress", "--no-tensorboard"]


# ----------------------------------------------------------------- settings

@pytest.mark.parametrize("changes, field", [
    (dict(etas=((0.1,),), seeds=(0,)), "pbt_every"),  # one member
    (dict(algo="naive", etas=((0.1,),)), "pbt_every"),
    (dict(etas=((0.1,), ("auto",))), "pbt_every"),
    (dict(pbt_fraction=0.6), "pbt_fraction"),
    (dict(pbt_fraction=0.0), "pbt_fraction"),
    (dict(pbt_every=-1), "pbt_every"),
    (dict(pbt_factors=(0.8, -1.0)), "pbt_factors"),
    (dict(pbt_resample=1.5), "pbt_resample"),
    (dict(pbt_every=0, pbt_fraction=0.5), "pbt_fraction"),  # a PBT setting without PBT
])
def test_bad_pbt_settings_are_refused_by_name(changes, field):
    settings = {**dict(etas=((0.1,), (0.9,)), seeds=(0, 1), pbt_every=2), **changes}
    with pytest.raises(ConfigError) as err:
        make_config("tiny", **settings)
    assert err.value.field == field


def test_the_cli_refuses_pbt_of_one_member_before_making_a_folder(tmp_path):
    with pytest.raises(ConfigError, match="^pbt_every: .*at least 2 members"):
        main(["--preset", "tiny", "--pbt-every", "2", "--out", str(tmp_path / "never"), "--no-progress"])
    assert not (tmp_path / "never").exists()


# ------------------------------------------------------------ by hand

def test_fitness_is_the_mean_fraction_of_stages_completed():
    # 4 episodes of 3 stages: all entered stage 0, 3 reached stage 1, 2 stage 2, 1 succeeded: (3 + 2 + 1) / 12.
    window = EpisodeStats(episodes=jnp.float32(4), successes=jnp.float32(1), stages=jnp.array([4.0, 3.0, 2.0]))
    np.testing.assert_allclose(fitness(window), 0.5)
    none = EpisodeStats(episodes=jnp.float32(0), successes=jnp.float32(0), stages=jnp.zeros(3))
    assert fitness(none) == 0.0


def test_selection_replaces_the_bottom_by_the_top_and_leaves_padding_alone():
    fit = jnp.array([0.1, 0.9, 0.5, 0.0, 0.7, 0.3, 0.2, 0.6, 0.0, 0.0])  # 8 members and 2 padded slots
    keys = jax.random.split(jax.random.PRNGKey(0), 10)
    source, copied, bottom = map(np.asarray, select(fit, keys, 0.25, grid_size=8))
    np.testing.assert_array_equal(np.sort(bottom), [0, 3])
    np.testing.assert_array_equal(np.nonzero(copied)[0], [0, 3])  # the two least fit
    assert set(source[[0, 3]]) <= {1, 4}  # from the two fittest
    keep = [1, 2, 4, 5, 6, 7, 8, 9]
    np.testing.assert_array_equal(source[keep], keep)
    # A population without a fitter member keeps every member (all at 0 before any episode ends).
    source, copied, _ = select(jnp.zeros(8), keys[:8], 0.25, grid_size=8)
    assert not copied.any() and (source == jnp.arange(8)).all()


def _hand_state(fit: np.ndarray, eta: np.ndarray) -> TrainState:
    """A grid state of len(fit) members whose leaves say which member they belong to, and whose windows
    have the fitness `fit` (3 agents: successes = 3 × fit of one episode)."""
    members, agents = eta.shape
    ids = jnp.arange(members, dtype=jnp.float32)
    window = EpisodeStats(episodes=jnp.ones(members), successes=jnp.asarray(3 * fit, jnp.float32),
                          stages=jnp.zeros((members, agents)).at[:, 0].set(1.0))
    return TrainState(agents={"actor": ids[:, None] * jnp.ones((members, 4)), "log_alpha": -ids[:, None] * jnp.ones((members, agents))},
                      buffer={"obs": ids[:, None, None] * jnp.ones((members, 5, 2))},
                      env_state={"pos": 10 * ids}, key=jax.random.split(jax.random.PRNGKey(3), members),
                      env_steps=jnp.full(members, 400, jnp.int32), epoch=jnp.full(members, 2, jnp.int32),
                      eta_auto=jnp.zeros((members, agents)), successor_succeeded=jnp.zeros((members, agents), bool),
                      pbt=PbtMember(eta=jnp.asarray(eta, jnp.float32), window=window))


def test_exploit_copies_exactly_the_chosen_members_and_explores_their_ratios():
    config = make_config("tiny", rooms=3, etas=((0.1,), (0.9,)), seeds=tuple(range(4)), pbt_every=2)
    fit = np.array([0.2, 1.0, 0.4, 0.0, 0.6, 0.8, 0.1, 0.5])
    eta = np.stack([np.linspace(0.2, 0.7, 8), np.linspace(0.6, 0.3, 8), np.ones(8)], axis=1).astype(np.float32)
    state = _hand_state(fit, eta)
    new, record = jax.jit(exploit_explore, static_argnums=(1, 2))(state, config, 8)
    state, new, record = jax.device_get((state, new, record))
    parent = record.parent
    copied = np.nonzero(parent >= 0)[0]
    np.testing.assert_array_equal(copied, [3, 6])  # the two least fit ...
    assert set(parent[copied]) <= {1, 5}  # ... copy the two fittest
    source = np.where(parent >= 0, parent, np.arange(8))
    for name in ("agents", "buffer", "env_state", "env_steps", "epoch"):
        for old, got in zip(jax.tree.leaves(getattr(state, name)), jax.tree.leaves(getattr(new, name))):
            np.testing.assert_array_equal(got, old[source])  # the donor's rows, every other member untouched
    kept = parent < 0
    np.testing.assert_array_equal(new.key[kept], state.key[kept])
    assert len({tuple(k) for k in new.key}) == 8  # a copy's key is neither its donor's nor another copy's
    np.testing.assert_array_equal(new.pbt.eta[kept], eta[kept])
    moved = new.pbt.eta[copied]
    assert ((moved >= 0) & (moved <= 1)).all()
    assert (moved[:, :2] != eta[source[copied], :2]).all()  # explored (0.8 or 1.25 ×, or redrawn)
    np.testing.assert_array_equal(moved[:, 2], 1.0)  # the last agent has no next critic
    np.testing.assert_array_equal(record.eta, new.pbt.eta)
    np.testing.assert_allclose(record.fitness, fit, rtol=1e-6)
    assert not any(np.any(x) for x in jax.tree.leaves(new.pbt.window))  # every window starts anew


def test_pbt_step_ranks_only_every_k_epochs():
    config = make_config("tiny", etas=((0.1,), (0.9,)), seeds=(0, 1), pbt_every=3)
    state = _hand_state(np.array([0.0, 1.0, 0.5, 0.2]), np.array([[0.1, 1.0]] * 2 + [[0.9, 1.0]] * 2))
    step = jax.jit(pbt_step, static_argnums=(1, 2))
    same, record = step(state, config, 4)  # epoch 2
    assert (record.parent == -1).all()
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(same)):
        np.testing.assert_array_equal(a, b)
    _, record = step(state.replace(epoch=state.epoch + 1), config, 4)
    np.testing.assert_array_equal(record.parent, [1, -1, -1, -1])


def test_perturbation_multiplies_or_redraws_within_the_unit_interval():
    config = make_config("tiny", etas=((0.1,), (0.9,)), seeds=(0, 1), pbt_every=1, pbt_resample=0.25)
    eta = jnp.tile(jnp.array([[0.5, 0.9, 1.0]]), (4000, 1))
    moved = np.asarray(perturb(eta, jax.random.split(jax.random.PRNGKey(1), 4000), config))
    assert ((moved >= 0) & (moved <= 1)).all()
    np.testing.assert_array_equal(moved[:, 2], 1.0)
    first = moved[:, 0]
    multiplied = np.isclose(first, 0.4) | np.isclose(first, 0.625)
    assert abs((~multiplied).mean() - 0.25) < 0.03  # redrawn with pbt_resample's probability
    assert abs(np.isclose(first, 0.4).mean() - 0.375) < 0.03  # else either factor at even odds
    assert abs((moved[:, 1] == 1.0).mean() - 0.375) < 0.03  # 0.9 × 1.25, clipped to 1


# ------------------------------------------------------------- whole runs

@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("pbt") / "run"
    main(CLI + ["--out", str(out), "--checkpoint-every", "1"])
    return out


def test_a_pbt_run_writes_its_lineage(cli_run):
    rows = outputs.read_rows(cli_run / "metrics.jsonl")
    assert len(rows) == 12
    by = {(r["epoch"], r["member"]): r for r in rows}
    copies = 0
    for epoch in (1, 2, 3):
        for m in range(4):
            r = by[epoch, m]
            before = by[epoch - 1, m]["pbt_eta"] if epoch > 1 else r["eta"]
            np.testing.assert_allclose(r["eta_used"][0], before[0], rtol=1e-5)  # trained with what it held
            if r["pbt_parent"] < 0:
                np.testing.assert_array_equal(np.float32(r["pbt_eta"]), np.float32(before))  # kept its ratios
            else:
                copies += 1
                assert by[epoch, r["pbt_parent"]]["pbt_fitness"] > r["pbt_fitness"]
                assert 0.0 <= r["pbt_eta"][0] <= 1.0 and r["pbt_eta"][1] == 1.0
        assert sum(by[epoch, m]["pbt_parent"] >= 0 for m in range(4)) <= 1  # ⌊0.25 × 4⌋
    assert copies >= 1
    summary = json.loads((cli_run / "summary.json").read_text())
    assert [m["pbt_eta"] for m in summary["members"]] == [by[3, m]["pbt_eta"] for m in range(4)]
    out = plot.main([str(cli_run), "--lineage"])
    assert out == cli_run / "lineage.png" and out.stat().st_size > 10_000
    founders = plot.load_lineage(cli_run).founders
    assert founders.shape == (3, 4) and set(founders.ravel()) <= {0, 1, 2, 3}


def test_a_copy_carries_its_donors_founder():
    # Epoch 1: member 2 copies 0; epoch 2: member 1 copies 2 (now 0's line); epoch 3: nothing.
    parent = np.array([[-1, -1, 0], [-1, 2, -1], [-1, -1, -1]])
    data = plot.Lineage(env_steps=np.array([1, 2, 3]), eta=np.zeros((3, 3, 2)), parent=parent, start=np.zeros((3, 2)))
    np.testing.assert_array_equal(data.founders, [[0, 1, 0], [0, 0, 0], [0, 0, 0]])


def test_a_fixed_ratio_run_has_no_lineage(tmp_path):
    with pytest.raises(ValueError, match="not a PBT run"):
        rows = [{"member": 0, "epoch": 1, "eta": [0.1, 1.0]}]
        (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        plot.load_lineage(tmp_path)


def test_resume_reproduces_the_uninterrupted_pbt_run(tmp_path, cli_run):
    """Killed after epoch 3's rows but before its checkpoint: epoch 3 (with its ranking) is trained again."""
    out = tmp_path / "killed"
    run(CONFIG, out, progress=False, checkpoint_every=2, tensorboard=False)
    shutil.rmtree(out / "checkpoints" / "3")
    main(["--resume", str(out), "--no-progress", "--no-tensorboard"])
    strip = lambda rows: [{k: v for k, v in r.items() if k != "epoch_wall_s"} for r in rows]
    rows = strip(outputs.read_rows(out / "metrics.jsonl"))
    assert rows == strip(outputs.read_rows(cli_run / "metrics.jsonl"))
    assert any(r["pbt_parent"] >= 0 for r in rows if r["epoch"] == 3)  # the epoch trained again copied a member
    (epoch_a, a), (epoch_b, b) = latest_state(cli_run, CONFIG), latest_state(out, CONFIG)
    assert epoch_a == epoch_b == 3
    assert a.pbt is not None
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)
