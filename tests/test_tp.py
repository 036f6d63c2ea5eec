"""TP baseline (--algo tp): proximity targets and loss, buffers, GAE, learning on a toy, the CLI, bad input."""
import json

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccp_jax.config import Config, ConfigError, make_config
from ccp_jax.train import Args, config_from_args, main
from ccp_jax.grid import GridTrainer
from ccp_jax.tp.networks import Proximity, TransitionPolicy, Value, norm_init, normalise
from ccp_jax.tp.ppo import gae
from ccp_jax.tp.primitives import Primitives
from ccp_jax.tp.proximity import ProximityData, buffer_add, buffer_init, proximity_loss, proximity_targets
from ccp_jax.tp.rollout import TPNets, TPParams, control_init, make_initial_successes, make_rollout
from ccp_jax.tp.trainer import make_tp_train
from toy_env import Line

DELTA = 0.95


class Threshold(nn.Module):
    """Scripted primitive on the Line: full speed right if x >= its threshold, else full speed left."""

    @nn.compact
    def __call__(self, obs):
        threshold = self.param("threshold", nn.initializers.zeros, ())
        mean = jnp.where(obs[..., 0] >= threshold, 5.0, -5.0)[..., None]
        return mean, jnp.zeros_like(mean)


def scripted(thresholds) -> Primitives:
    """Primitive n runs right only from x >= thresholds[n] (Line moves 0.25 per step at full speed)."""
    return Primitives(actor=Threshold(), params={"params": {"threshold": jnp.asarray(thresholds, jnp.float32)}})


def test_proximity_targets_by_hand():
    labels = proximity_targets(jnp.array([4, 2, 0]), jnp.array([True, False, True]), 6, DELTA)
    np.testing.assert_allclose(labels[0], [DELTA ** 3, DELTA ** 2, DELTA, 1.0, 0.0, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(labels[1], np.zeros(6))  # a failed transition: every state 0
    np.testing.assert_array_equal(labels[2], np.zeros(6))  # nothing stored


def test_predictor_loss_is_per_sample():
    p_s, y = jnp.array([0.5, 0.9, 7.0]), jnp.array([1.0, 0.9, 0.0])
    w_s = jnp.array([1.0, 1.0, 0.0])  # the third sample is padding from an empty buffer
    p_f, w_f = jnp.array([0.2, 0.4]), jnp.ones(2)
    loss = proximity_loss(p_s, y, w_s, p_f, w_f)
    expected = ((0.5 - 1.0) ** 2 + 0.0) / 2 + (0.2 ** 2 + 0.4 ** 2) / 2
    np.testing.assert_allclose(loss, expected, rtol=1e-6)
    # The released code's broadcast [B, 1] − [B] would compare every prediction with every label.
    broadcast = np.mean((np.array([0.5, 0.9])[:, None] - np.array([1.0, 0.9])[None, :]) ** 2) + 0.1
    assert abs(float(loss) - broadcast) > 1e-3


def test_buffer_add_places_segments_consecutively():
    buf = buffer_init(2, 8, 1)
    obs = jnp.arange(2 * 3, dtype=jnp.float32).reshape(2, 3, 1) + 1.0  # env 0: 1, 2, 3; env 1: 4, 5, 6
    buf = buffer_add(buf, obs, jnp.ones((2, 3)), slot=jnp.array([1, 1]), count=jnp.array([2, 3]))
    np.testing.assert_array_equal(buf.size, [0, 5])
    np.testing.assert_array_equal(buf.obs[1, :6, 0], [1, 2, 4, 5, 6, 0])
    buf = buffer_add(buf, obs, jnp.ones((2, 3)), slot=jnp.array([0, 1]), count=jnp.array([0, 3]))
    np.testing.assert_array_equal(buf.size, [0, 8])
    np.testing.assert_array_equal(buf.obs[1, :, 0], [1, 2, 4, 5, 6, 4, 5, 6])
    buf = buffer_add(buf, obs, jnp.ones((2, 3)), slot=jnp.array([0, 1]), count=jnp.array([0, 1]))
    np.testing.assert_array_equal(buf.obs[1, :, 0], [4, 2, 4, 5, 6, 4, 5, 6])  # full: the ring wraps to row 0
    np.testing.assert_array_equal(buf.ptr, [0, 1])


def test_gae_skips_primitive_steps_and_stops_at_segment_ends():
    # One env: transition steps at t = 0, 1 (segment ends at 1), a primitive step at t = 2, a new segment at t = 3
    # still running when the rollout ends (bootstraps from last_value).
    r = jnp.array([[1.0], [2.0], [0.0], [3.0]])
    v = jnp.array([[0.5], [0.25], [9.0], [1.0]])
    end = jnp.array([[0.0], [1.0], [0.0], [0.0]])
    valid = jnp.array([[1.0], [1.0], [0.0], [1.0]])
    g, lam = 0.9, 0.8
    adv, ret = gae(r, v, end, valid, jnp.array([2.0]), g, lam)
    a1 = 2.0 - 0.25
    a0 = (1.0 + g * 0.25 - 0.5) + g * lam * a1
    a3 = 3.0 + g * 2.0 - 1.0
    np.testing.assert_allclose(adv[:, 0], [a0, a1, 0.0, a3], rtol=1e-6)
    np.testing.assert_allclose(ret[:, 0], [a0 + 0.5, a1 + 0.25, 0.0, a3 + 1.0], rtol=1e-6)


def _line_config(**overrides):
    base = dict(algo="tp", primitives="scripted", steps_per_epoch=200, num_envs=4, max_episode_steps=40,
                tp_max_steps=3, tp_buffer_size=256, tp_init_episodes=4)
    return make_config("tiny", **{**base, **overrides})


def _hand_set_transition(config, env):
    """A transition policy that always moves right at full speed and never chooses to terminate."""
    nets = TPNets(policy=TransitionPolicy(config.tp.tp_hidden, 1), value=Value(config.tp.tp_hidden),
                  proximity=Proximity(config.tp.tp_prox_hidden), primitives=None)
    params = nets.policy.init(jax.random.PRNGKey(0), jnp.zeros((env.observation_size,)))
    params = jax.tree.map(jnp.zeros_like, params)
    head = params["params"]["TanhMLP_0"]["Dense_2"]
    head["bias"] = jnp.array([5.0, 20.0, -20.0])  # mean 5 (clipped to 1), "continue" ≫ "terminate"
    params["params"]["log_std"] = jnp.full((1,), -20.0)
    prox = nets.proximity.init(jax.random.PRNGKey(1), jnp.zeros((env.observation_size,)))
    stack = lambda t: jax.tree.map(lambda x: x[None], t)
    norm = jax.tree.map(lambda x: x[None], norm_init(env.observation_size))
    return nets, TPParams(policy=stack(params), proximity=stack(prox), norm=norm)


@pytest.mark.parametrize("thresholds", [(0.0, 0.0, 0.0), (0.0, 0.0, 9.0)])
def test_initial_successes_keep_the_first_states_of_each_completed_stage(thresholds):
    """The permanent success states against a plain loop over the same episodes. Primitives all run right
    (every stage completed), or the last one runs left from stage 2 (stage 2 never completed: predictor 1
    gets nothing)."""
    config = _line_config(rooms=3, max_episode_steps=30, tp_init_episodes=5, tp_init_fraction=0.3)
    env, primitives = Line(3, 30), scripted(list(thresholds))
    key = jax.random.PRNGKey(7)
    permanent, steps = jax.jit(make_initial_successes(config, env, primitives))(key)

    step = jax.jit(env.step)
    states = [jax.tree.map(lambda x, i=i: x[i], jax.vmap(env.reset)(jax.random.split(key, 5))) for i in range(5)]
    trace = []  # per episode: (t, obs, stage) of every live state
    for state in states:
        visited = []
        for t in range(30):
            if state.done:
                break
            visited.append((t, np.asarray(state.obs), int(state.info["stage"])))
            x = float(state.obs[0])
            state = step(state, jnp.array([np.tanh(5.0 if x >= thresholds[visited[-1][2]] else -5.0)]))
        completed = [int(state.info["stage"]) > k or bool(state.metrics["success"]) for k in range(3)]
        trace.append((visited, completed))
    expected = {0: [], 1: []}
    for t in range(30):
        for visited, completed in trace:
            for u, obs, stage in visited:
                in_stage = [v for v, _, k in visited if k == stage]
                keep = int(np.ceil(0.3 * len(in_stage))) if completed[stage] else 0
                if u == t and stage >= 1 and u - in_stage[0] < keep:
                    expected[stage - 1].append(obs)
    assert int(steps) == sum(len(v) for v, _ in trace)
    for k in (0, 1):
        assert int(permanent.size[k]) == len(expected[k])
        np.testing.assert_allclose(permanent.obs[k, :len(expected[k])], np.reshape(expected[k], (-1, 3)), atol=1e-6)
    assert len(expected[0]) > 0 and (len(expected[1]) > 0) == (thresholds[2] == 0.0)


@pytest.mark.parametrize("succeeds", [True, False])
def test_rollout_labels_a_hand_made_transition(succeeds):
    """Primitive 0 runs right into stage 1 (x >= 1); the transition moves +0.25 three times, is forced to
    terminate at the 4th state, then primitive 1 (threshold 1.5, or unreachable 9) succeeds or fails."""
    config = _line_config(num_envs=1, steps_per_epoch=40)
    env = Line(2, 40)
    nets, params = _hand_set_transition(config, env)
    nets = nets._replace(primitives=scripted([0.0, 1.5 if succeeds else 9.0]))
    rollout = jax.jit(make_rollout(config, env, nets))
    empty = buffer_init(1, 64, env.observation_size)
    env_state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), 1))
    x0 = float(env_state.obs[0, 0])
    _, ctrl, data, samples, stats = rollout(params, env_state, control_init(1, config.tp.tp_max_steps + 1, 3),
                                            ProximityData(empty, empty, empty), jax.random.PRNGKey(4))
    prim_step = 0.25 * np.tanh(5.0)  # the scripted primitive's deterministic step; the transition's is 0.25
    first_in_stage_1 = x0 + prim_step * np.ceil((1.0 - x0) / prim_step)  # where primitive 0 hands over
    xs = first_in_stage_1 + 0.25 * np.arange(4)
    stored, other = (data.success, data.failure) if succeeds else (data.failure, data.success)
    # A successful episode takes ~8 steps, so the 40-step rollout holds several, each storing 4 states;
    # the failing one lasts until the time limit (40 steps): one segment.
    segments = int(stored.size[0]) // 4
    assert int(stored.size[0]) == 4 * segments and int(other.size[0]) == 0
    assert segments >= 3 if succeeds else segments == 1
    np.testing.assert_allclose(stored.obs[0, :4, 0], xs, atol=1e-5)  # the first episode's transition
    expected = [DELTA ** 3, DELTA ** 2, DELTA, 1.0] if succeeds else [0.0] * 4
    np.testing.assert_allclose(stored.label[0, : 4 * segments], np.tile(expected, segments), rtol=1e-6)
    assert float(np.asarray(samples.valid).sum()) == 4 * segments  # 3 moves + the forced termination each
    assert float(stats.forced[0]) == segments == float(stats.handovers[0])
    assert float(stats.won[0]) == segments * succeeds and float(stats.lost[0]) == segments * (not succeeds)
    assert int(ctrl.pending_len[0]) == 0


LEARN = _line_config(seeds=(0, 1), total_steps=8000, tp_prox_updates=50, tp_ppo_epochs=4, tp_lr=1e-3,
                     tp_prox_lr=1e-3, eval_episodes=8)


@pytest.fixture(scope="module")
def learned():
    """Primitive 1 only succeeds from x >= 1.5; primitive 0 hands over at x in [1, 1.25). With at most
    3 transition steps the transition policy cannot finish the task itself: it must hand over at x >= 1.5."""
    env = Line(2, 40)
    trainer = GridTrainer(LEARN, env, trainer=make_tp_train(LEARN, env, scripted([0.0, 1.5])))
    eta, seed = LEARN.grid_arrays()
    state = trainer.init(jnp.asarray(seed))
    avals = _avals(state)
    history = []
    for _ in range(LEARN.num_epochs):
        state, metrics = trainer.train_step(state, jnp.asarray(eta))
        history.append(jax.device_get(metrics))
    assert _avals(state) == avals  # every epoch reuses the first epoch's compiled program
    return trainer, jax.device_get(state), history


def _avals(tree):
    return jax.tree.map(lambda x: (x.shape, x.dtype, x.weak_type), tree)


def test_transition_policy_learns_the_hand_over_state(learned):
    trainer, state, history = learned
    success = np.array([m.eval.success_rate for m in history])  # [epochs, seeds]
    assert success[0].max() == 0.0  # the primitives alone (and the untrained transition) always fail
    assert success[-5:].mean() >= 0.9, success[-5:]
    # The predictor has learnt where primitive 1 succeeds from: x >= 1.5 scores above x just past the wall.
    for member in range(LEARN.grid_size):
        params = jax.tree.map(lambda x: x[member, 0], state.predictors.params)
        norm = jax.tree.map(lambda x: x[member, 0], state.agents.norm)
        obs = jnp.array([[1.05, 0, 0], [1.7, 0, 0]])
        p = trainer.networks.proximity.apply(params, normalise(norm, obs))
        assert float(p[1]) > float(p[0]) + 0.2, p
    # Env steps are counted per env step, primitive and transition alike.
    np.testing.assert_array_equal(history[-1].env_steps, [LEARN.budget.total_steps] * LEARN.grid_size)


def test_grid_member_equals_the_run_alone(learned):
    """Seeds are a vmapped axis: member 1 of the grid trains exactly as seed 1 alone."""
    _, _, history = learned
    alone = LEARN.replace(seeds=(1,), total_steps=2 * LEARN.budget.steps_per_epoch)
    env = Line(2, 40)
    trainer = GridTrainer(alone, env, trainer=make_tp_train(alone, env, scripted([0.0, 1.5])))
    eta, seed = alone.grid_arrays()
    state = trainer.init(jnp.asarray(seed))
    for epoch in range(2):
        state, metrics = trainer.train_step(state, jnp.asarray(eta))
        for a, b in zip(jax.tree.leaves(jax.device_get(metrics)), jax.tree.leaves(history[epoch])):
            np.testing.assert_allclose(a[0], b[1], rtol=1e-4, atol=1e-5)


@pytest.fixture(scope="module")
def primitives_run(tmp_path_factory):
    """A tiny naive run on the 2-room maze: the primitives for the CLI tests."""
    out = tmp_path_factory.mktemp("prims") / "naive"
    main(["--preset", "tiny", "--algo", "naive", "--out", str(out), "--no-progress", "--no-tensorboard"])
    return out


def test_cli_runs_tp_and_writes_the_contract_files(primitives_run, tmp_path):
    out = tmp_path / "tp"
    summary = main(["--preset", "tiny", "--algo", "tp", "--primitives", str(primitives_run), "--seeds", "2",
                    "--out", str(out), "--no-progress", "--no-tensorboard"])
    config = json.loads((out / "config.json").read_text())
    assert config["algo"] == "tp" and config["tp"]["primitives"] == str(primitives_run.resolve())
    assert config["tp"]["tp_max_steps"] == 10 and config["grid"]["seeds"] == [0, 1]
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2 * config["num_epochs"]
    for key in ("member", "seed", "epoch", "env_steps", "success_rate", "eval_return", "stage_reached_mean",
                "stage_fraction", "train_stage_fraction", "tp_samples", "tp_won", "tp_lost", "prox_loss", "pi_loss", "v_loss",
                "tp_eval_transition_fraction", "tp_init_env_steps"):
        assert key in rows[0], key
    assert len(rows[0]["tp_samples"]) == 1 and len(rows[0]["stage_fraction"]) == 2 and "pocket" in rows[0]["eval_end"]
    assert all(r["train_stage_fraction"][0] == 1.0 for r in rows if r["train_episodes"])
    assert [r["env_steps"] for r in rows if r["member"] == 0] == [200, 400]
    assert all(np.isfinite(r["prox_loss"][0]) and np.isfinite(r["pi_loss"][0]) for r in rows)
    saved = json.loads((out / "summary.json").read_text())
    assert [m["algo"] for m in saved["members"]] == ["tp", "tp"] == [m["algo"] for m in summary["members"]]
    assert (out / "checkpoints").is_dir()
    # Stopping after one epoch and resuming gives the same second epoch, bit for bit.
    part = tmp_path / "part"
    args = ["--preset", "tiny", "--algo", "tp", "--primitives", str(primitives_run), "--seeds", "2", "--no-progress",
            "--no-tensorboard"]
    main(args + ["--out", str(part), "--total-steps", "200"])
    main(["--resume", str(part), "--total-steps", "400", "--no-progress", "--no-tensorboard"])
    resumed = [json.loads(line) for line in (part / "metrics.jsonl").read_text().splitlines()]
    strip = lambda r: {k: v for k, v in r.items() if k != "epoch_wall_s"}
    assert [strip(r) for r in resumed] == [strip(r) for r in rows]


def _fake_run(path, **fields):
    """A run folder with only a config.json (enough for every check that precedes loading)."""
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps(make_config("tiny", **fields).to_dict()))
    return path


@pytest.mark.parametrize("setup, argv, field", [
    (None, [], "primitives"),  # no --primitives at all
    ("missing", [], "primitives"),
    ("naive3", [], "primitives"),  # 3-room primitives for a 2-room run
    ("csac", [], "primitives"),  # not a naive run
    ("naive_stop", [], "maze_slide"),  # primitives of a robot that stops at walls
    ("naive2", ["--primitives-member", "5"], "primitives_member"),
    ("naive2", [], "primitives"),  # no checkpoints/
    ("naive2", ["--tp-max-steps", "0"], "tp_max_steps"),
    ("naive2", ["--eta", "0.1", "0.5"], "eta"),
])
def test_bad_tp_input_fails_before_compiling(tmp_path, setup, argv, field):
    runs = {"naive3": dict(algo="naive", rooms=3), "csac": dict(algo="csac"), "naive2": dict(algo="naive"),
            "naive_stop": dict(algo="naive", maze_slide=False)}
    args = ["--preset", "tiny", "--algo", "tp", "--out", str(tmp_path / "out"), "--no-progress"] + argv
    if setup == "missing":
        args += ["--primitives", str(tmp_path / "nowhere")]
    elif setup is not None:
        args += ["--primitives", str(_fake_run(tmp_path / setup, **runs[setup]))]
    with pytest.raises(ConfigError) as err:
        main(args)
    assert err.value.field == field, err.value
    assert not (tmp_path / "out").exists()  # refused before the run folder (and any compile)


def test_tp_config_round_trips():
    config = make_config("tiny", algo="tp", primitives="/runs/naive", tp_hidden=(8, 8))
    assert Config.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    with pytest.raises(ConfigError, match="^tp_delta:"):
        config.replace(tp_delta=1.0)
    c = config_from_args(Args(preset="tiny"))
    assert c.algo == "csac" and c.tp.primitives is None
