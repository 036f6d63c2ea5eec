"""Checkpoint and resume: identity with an uninterrupted run, crash safety, clear errors."""
import json
import shutil
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccp_jax import checkpoint
from ccp_jax.config import ConfigError, make_config
from ccp_jax.envs import make_env
from ccp_jax.train import main, run
from ccp_jax.grid import make_grid_train
from saved import latest_state  # tests/ is on sys.path (conftest)

# 3 epochs, 2 members; the running normaliser and an "auto" ratio (the trusted rule's, which moves every
# epoch) put their state into the checkpoint too.
CONFIG = make_config("tiny", etas=((0.1,), ("auto",)), seeds=(0,), normaliser="ema", total_steps=600,
                     eta_auto_rule="trusted")


def _rows(run_dir):
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    for r in rows:
        r.pop("epoch_wall_s")
    return rows


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    run(CONFIG, out, progress=False, checkpoint_every=1)
    return out


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory):
    """A run killed after writing epoch 3's metrics but before its checkpoint (the last one is epoch 2)."""
    out = tmp_path_factory.mktemp("killed")
    run(CONFIG, out, progress=False, checkpoint_every=2)
    shutil.rmtree(out / "checkpoints" / "3")
    # A save that was killed mid-write leaves only orbax's temporary folder behind.
    shutil.copytree(out / "checkpoints" / "2", out / "checkpoints" / "3.orbax-checkpoint-tmp-1700000000")
    for f in (out / "checkpoints" / "3.orbax-checkpoint-tmp-1700000000").rglob("*"):
        if f.is_file():
            f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 2])
    return out


def test_resume_reproduces_the_uninterrupted_run(uninterrupted, interrupted):
    assert len(_rows(interrupted)) == 6  # epoch 3 rows exist but the state after epoch 3 was lost
    main(["--resume", str(interrupted), "--no-progress"])
    assert _rows(interrupted) == _rows(uninterrupted)
    (e1, a), (e2, b) = latest_state(uninterrupted, CONFIG), latest_state(interrupted, CONFIG)
    assert e1 == e2 == 3
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)


def test_a_row_cut_by_a_crash_is_trained_again_not_left_out(tmp_path, uninterrupted):
    out = tmp_path / "run"
    shutil.copytree(uninterrupted, out)  # checkpoints of epochs 2 and 3
    text = (out / "metrics.jsonl").read_text()
    (out / "metrics.jsonl").write_text(text[: text.rindex("{") + 40])  # epoch 3's last row cut mid-write
    main(["--resume", str(out), "--no-progress"])
    assert _rows(out) == _rows(uninterrupted)  # from checkpoint 2, epoch 3 trained again
    assert latest_state(out, CONFIG)[0] == 3


def test_a_damaged_row_is_refused_and_nothing_changes(tmp_path, uninterrupted):
    out = tmp_path / "run"
    shutil.copytree(uninterrupted, out)
    lines = (out / "metrics.jsonl").read_text().splitlines(keepends=True)
    lines[2] = lines[2][:30] + "\n"
    (out / "metrics.jsonl").write_text(damaged := "".join(lines))
    with pytest.raises(ConfigError, match="^resume: .*metrics.jsonl line 3 is not a JSON row"):
        main(["--resume", str(out), "--no-progress"])
    assert (out / "metrics.jsonl").read_text() == damaged
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["2", "3"]


def test_resume_can_extend_the_budget(tmp_path, uninterrupted):
    out = tmp_path / "run"
    shutil.copytree(uninterrupted, out)
    earlier = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    for r in earlier:
        r["epoch_wall_s"] = 1000.0  # as if each of the 3 epochs had taken 1000 s
    (out / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in earlier))
    main(["--resume", str(out), "--total-steps", "800", "--no-progress"])
    wall = json.loads((out / "summary.json").read_text())["wall_s"]
    assert 3000 < wall < 3000 + 600  # the earlier epochs' time plus this invocation's
    rows = _rows(out)
    assert [r["epoch"] for r in rows] == [1, 1, 2, 2, 3, 3, 4, 4]
    assert rows[:6] == _rows(uninterrupted)
    assert json.loads((out / "config.json").read_text())["budget"]["total_steps"] == 800


def test_mismatched_config_is_refused_and_nothing_changes(uninterrupted):
    before = (uninterrupted / "metrics.jsonl").read_bytes()
    for argv, field in ((["--rooms", "3"], "rooms"), (["--hidden", "32", "32"], "hidden"),
                        (["--algo", "naive"], "algo"), (["--eta", "0.5"], "etas"),
                        (["--normaliser", "batch"], "normaliser")):
        with pytest.raises(ConfigError) as err:
            main(["--resume", str(uninterrupted), "--no-progress"] + argv)
        assert err.value.field == field
    assert (uninterrupted / "metrics.jsonl").read_bytes() == before


def test_corrupt_checkpoints_give_a_clear_error(tmp_path, uninterrupted):
    """With every checkpoint damaged, nothing is left to resume from (one damaged checkpoint gives way to the
    older one: tests/test_run_folders.py)."""
    out = tmp_path / "run"
    shutil.copytree(uninterrupted, out)
    for f in (out / "checkpoints").rglob("*"):
        if f.is_file() and f.stat().st_size > 64:
            f.write_bytes(b"\0" * 16)
    before = (out / "metrics.jsonl").read_bytes()
    with pytest.raises(checkpoint.CheckpointError, match="checkpoints/2 cannot be restored"):
        main(["--resume", str(out), "--no-progress"])
    assert (out / "metrics.jsonl").read_bytes() == before
    with pytest.raises(ConfigError, match="^resume:"):
        main(["--resume", str(tmp_path / "nothing"), "--no-progress"])


class Agents(NamedTuple):
    actor: dict


class Toy(NamedTuple):
    """The shape of a grid's state for `checkpoint.save`: every leaf has the grid axis first."""
    agents: Agents
    steps: jax.Array
    empty: jax.Array  # zero-size, as MJX states have


@pytest.mark.parametrize("slots", [3, 6])
def test_a_grid_padded_for_other_devices_is_padded_anew(tmp_path, slots):
    """3 members saved padded to 4 (2 devices) restore into 3 slots (1 device) and 6 (3 devices of 2): the real
    members are kept and the padding is copies of member 2, whatever the saved padding held."""
    rows = jnp.array([[0.0, 10.0], [1.0, 11.0], [2.0, 12.0], [-1.0, -1.0]])  # slot 3: the old padding
    saved = Toy(Agents({"w": rows}), jnp.array([5, 6, 7, -1]), jnp.zeros((4, 0)))
    mngr = checkpoint.manager(tmp_path)
    checkpoint.save(mngr, 1, saved)
    want_rows = np.array([[0.0, 10.0], [1.0, 11.0], [2.0, 12.0]] + [[2.0, 12.0]] * (slots - 3))
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct((slots,) + x.shape[1:], x.dtype), saved)
    epoch, got = checkpoint.restore(mngr, abstract, grid_size=3)
    assert epoch == 1
    np.testing.assert_array_equal(got.agents.actor["w"], want_rows)
    np.testing.assert_array_equal(got.steps, [5, 6, 7] + [7] * (slots - 3))
    assert got.empty.shape == (slots, 0)
    _, actor = checkpoint.restore(mngr, abstract.agents.actor, item="policy", grid_size=3)
    np.testing.assert_array_equal(actor["w"], want_rows)
    with pytest.raises(checkpoint.CheckpointError):  # without the grid size the padding cannot be redone
        checkpoint.restore(mngr, abstract)
    mngr.close()


def test_load_policy_acts_like_the_trained_actor(uninterrupted):
    from ccp_jax import load_policy
    from ccp_jax.collect import policy_mean_and_log_std
    from ccp_jax.networks import deterministic_action

    _, state = latest_state(uninterrupted, CONFIG)
    policy = load_policy(uninterrupted, member=1)
    obs = np.random.default_rng(0).normal(size=(5, 24)).astype(np.float32)
    stage = np.array([0, 1, 0, 1, 1], np.int32)
    actor = make_grid_train(CONFIG, make_env(CONFIG)).networks.actor
    params = jax.tree.map(lambda x: x[1], state.agents.actor)
    mean, _ = policy_mean_and_log_std(actor, params, obs, stage)
    np.testing.assert_allclose(policy(obs, stage), deterministic_action(mean), rtol=1e-6)
    assert policy(obs[0], stage[0]).shape == (2,)
    with pytest.raises(ValueError, match="^member:"):
        load_policy(uninterrupted, member=2)


def test_a_checkpoint_of_another_state_layout_is_refused_by_name(tmp_path):
    """A state with a leaf the checkpoint lacks (saved by an older version) gets a clear error, not a misread."""
    saved = Toy(Agents({"w": jnp.ones((2, 3))}), jnp.array([5, 6]), jnp.zeros((2, 0)))
    mngr = checkpoint.manager(tmp_path)
    checkpoint.save(mngr, 1, saved)
    grown = (saved, jnp.zeros((2, 4)))
    with pytest.raises(checkpoint.CheckpointError, match=r"lacks 3 of this version's state arrays \(#0/agents"):
        checkpoint.restore(mngr, jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), grown))
    mngr.close()


class Grown(NamedTuple):
    """`Toy` with a field added, as a later version's state would have it."""
    agents: Agents
    steps: jax.Array
    empty: jax.Array
    visits: jax.Array


def _abstract(tree):
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), tree)


def test_an_older_checkpoint_restores_into_a_state_with_an_added_field(tmp_path):
    """Leaves are found by path: an added field takes its initial value, named in a warning; the rest restore."""
    saved = Toy(Agents({"w": jnp.arange(6.0).reshape(2, 3)}), jnp.array([5, 6]), jnp.zeros((2, 0)))
    mngr = checkpoint.manager(tmp_path)
    checkpoint.save(mngr, 1, saved)
    init = Grown(Agents({"w": jnp.zeros((2, 3))}), jnp.zeros(2, jnp.int32), jnp.zeros((2, 0)), jnp.full((2, 4), 7.0))
    with pytest.warns(UserWarning, match="initial values: visits"):
        _, got = checkpoint.restore(mngr, _abstract(init), defaults=lambda: init)
    np.testing.assert_array_equal(got.agents.actor["w"], saved.agents.actor["w"])
    np.testing.assert_array_equal(got.steps, [5, 6])
    np.testing.assert_array_equal(got.visits, np.full((2, 4), 7.0))
    with pytest.raises(checkpoint.CheckpointError, match="lacks 1 of this version's state arrays \\(visits\\)"):
        checkpoint.restore(mngr, _abstract(init))  # no defaults: refused by name
    mngr.close()


def test_a_leaf_whose_shape_changed_is_refused_by_name(tmp_path):
    saved = Toy(Agents({"w": jnp.ones((2, 3))}), jnp.array([5, 6]), jnp.zeros((2, 0)))
    mngr = checkpoint.manager(tmp_path)
    checkpoint.save(mngr, 1, saved)
    wider = saved._replace(agents=Agents({"w": jnp.ones((2, 5))}))
    with pytest.raises(checkpoint.CheckpointError, match=r"array agents/actor/w is \(2, 3\) float32 where this "
                                                          r"version expects \(2, 5\) float32"):
        checkpoint.restore(mngr, _abstract(wider), defaults=lambda: wider)
    mngr.close()


class Gated(NamedTuple):
    agents: Agents
    steps: jax.Array
    successor_succeeded: jax.Array


def test_sacs_gate_saved_per_stage_restarts_from_its_initial_value(tmp_path):
    """SAC's checkpoints held `successor_succeeded` per stage where the state keeps one entry (its one agent has
    no successor): they resume with the initial value and a warning; any other reshaped leaf is still refused."""
    mngr = checkpoint.manager(tmp_path)
    checkpoint.save(mngr, 1, Gated(Agents({"w": jnp.ones((2, 3))}), jnp.array([5, 6]), jnp.ones((2, 2), bool)))
    init = Gated(Agents({"w": jnp.zeros((2, 3))}), jnp.zeros(2, jnp.int32), jnp.zeros((2, 1), bool))
    with pytest.warns(UserWarning, match=r"successor_succeeded was saved as \(2, 2\) .* starts from its initial"):
        _, got = checkpoint.restore(mngr, _abstract(init), defaults=lambda: init)
    np.testing.assert_array_equal(got.steps, [5, 6])
    np.testing.assert_array_equal(got.successor_succeeded, np.zeros((2, 1), bool))
    with pytest.raises(checkpoint.CheckpointError, match="successor_succeeded is \\(2, 2\\) bool"):
        checkpoint.restore(mngr, _abstract(init))  # no defaults to restart it from
    mngr.close()


def test_a_checkpoint_written_before_leaves_were_keyed_by_path_still_restores(tmp_path):
    """tests/fixtures/position_keyed_run: a Toy grid of 2 saved at epoch 3 by the code that keyed leaves by position."""
    run = tmp_path / "run"
    shutil.copytree(Path(__file__).parent / "fixtures" / "position_keyed_run", run)
    want = Toy(Agents({"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.array([[1.5], [2.5]])}),
               jnp.array([5, 6], jnp.int32), jnp.zeros((2, 0)))
    mngr = checkpoint.manager(run)
    epoch, got = checkpoint.restore(mngr, _abstract(want))
    assert epoch == 3
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_array_equal(a, b)
    _, actor = checkpoint.restore(mngr, _abstract(want.agents.actor), item="policy")
    np.testing.assert_array_equal(actor["b"], want.agents.actor["b"])
    grown = Grown(*want, jnp.zeros((2, 4)))
    with pytest.raises(checkpoint.CheckpointError, match="holds 3 arrays where this version's state has 4"):
        checkpoint.restore(mngr, _abstract(grown))  # by position, a changed layout cannot be matched
    mngr.close()
