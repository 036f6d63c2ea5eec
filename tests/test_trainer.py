"""The trainer end to end: shapes, grid = single runs, determinism, learning, CLI outputs."""
import json
import math
import types

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccp_jax.collect import auto_reset, make_evaluate, stage_counts
from ccp_jax.config import ConfigError, make_config
from ccp_jax.envs import make_env
from ccp_jax.networks import Actor
from ccp_jax.train import main
from ccp_jax.learner import critic_slots
from ccp_jax.devices import default_members_at_once
from ccp_jax.grid import make_grid_train
from ccp_jax.trainer import make_train
from toy_env import Line

GRID = make_config("tiny", rooms=2, etas=((0.1,), (0.9,)), seeds=(0, 1), total_steps=400)


def _train(config, trainer, epochs):
    eta, seed = config.grid_arrays()
    state = trainer.init(jnp.asarray(seed))
    history = []
    for _ in range(epochs):
        state, metrics = trainer.train_step(state, jnp.asarray(eta))
        history.append(jax.device_get(metrics))
    return jax.device_get(state), history


@pytest.mark.parametrize("vmapped", [False, True])
def test_auto_reset_replaces_exactly_the_finished_envs(vmapped):
    env, key = Line(2, 50), jax.random.PRNGKey(5)
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 3))
    moved = jax.vmap(env.step)(state, jnp.ones((3, 1)))
    fresh = jax.vmap(env.reset)(jax.random.split(key, 3))
    reset = jax.jit(jax.vmap(auto_reset, (None, 0, None)) if vmapped else auto_reset, static_argnums=0)
    stack = (lambda t: jax.tree.map(lambda x: jnp.stack([x, x]), t)) if vmapped else (lambda t: t)
    pick = (lambda x: x[0]) if vmapped else (lambda x: x)
    for done in ([0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]):
        out = reset(env, stack(moved.replace(done=jnp.array(done))), key)
        expected = np.where(np.array(done) > 0, fresh.pipeline_state, moved.pipeline_state)
        np.testing.assert_array_equal(pick(out.pipeline_state), expected)
        np.testing.assert_array_equal(pick(out.info["steps"]), np.where(np.array(done) > 0, 0, 1))


def test_stage_counts_count_ended_episodes_by_the_stages_they_reached():
    done, stage = jnp.array([1.0, 0.0, 1.0, 1.0, 1.0]), jnp.array([0, 2, 1, 2, 0])
    # ended: stages 0, 1, 2, 0 -> 4 reached stage 1 (index 0), 2 reached index 1, 1 reached index 2; env 1 runs on
    np.testing.assert_array_equal(stage_counts(done, stage, 3), [4.0, 2.0, 1.0])
    np.testing.assert_array_equal(stage_counts(jnp.zeros(5), stage, 3), [0.0, 0.0, 0.0])


def test_evaluation_acts_with_the_mean_or_with_the_policy_noise():
    """A policy of mean 0 and log-std 2 on the line (start x0 in [0, 0.2], steps of 0.25·a, 50 steps): its mean
    never moves, so every episode returns 50·x0; its samples (tanh of N(0, e²), mostly near ±1) random-walk
    across x = 1 into stage 2 in many of them."""
    config, env, actor = make_config("tiny", rooms=2), Line(2, 50), Actor((4,), 1)
    params = actor.init(jax.random.PRNGKey(0), jnp.zeros((1, 3)))
    head = params["params"]["MLP_0"]["Dense_1"]
    head["kernel"], head["bias"] = jnp.zeros_like(head["kernel"]), jnp.array([0.0, 2.0])
    agents = jax.tree.map(lambda x: jnp.stack([x, x]), params)  # both stages' agents
    key, episodes = jax.random.PRNGKey(7), 64
    mean = jax.jit(make_evaluate(config, env, actor, episodes=episodes))(agents, key)
    x0 = jax.vmap(env.reset)(jax.random.split(key, episodes)).pipeline_state  # the starts, from the same key
    np.testing.assert_allclose(mean.eval_return, 50 * x0.mean(), rtol=1e-5)
    np.testing.assert_array_equal(mean.stage_fraction, [1.0, 0.0])
    noisy = jax.jit(make_evaluate(config, env, actor, episodes=episodes, stochastic=True))
    first, again = noisy(agents, key), noisy(agents, key)
    np.testing.assert_array_equal(first.stage_fraction, again.stage_fraction)  # one key, the same episodes
    assert first.stage_fraction[0] == 1.0 and first.stage_fraction[1] > 0.2
    assert first.eval_return != mean.eval_return


@pytest.fixture(scope="module")
def grid_run():
    trainer = make_grid_train(GRID, make_env(GRID))
    return trainer, _train(GRID, trainer, 2)


def test_epoch_shapes_and_dtypes(grid_run):
    _, (state, history) = grid_run
    m = history[-1]
    g, n = GRID.grid_size, GRID.num_agents
    chex.assert_shape([m.eval.success_rate, m.eval.eval_return, m.env_steps], (g,))
    chex.assert_shape([m.train.q_loss, m.train.pi_loss, m.train.alpha, m.train.eta_star, m.buffer_size], (g, n))
    chex.assert_shape([m.eval.stage_fraction, m.train_stage_fraction], (g, 2))
    chex.assert_shape(state.buffer.data.obs, (g, n, GRID.sac.buffer_size, 24))
    assert state.buffer.data.obs.dtype == np.float32 and m.buffer_size.dtype == np.int32
    np.testing.assert_array_equal(m.env_steps, [400] * g)
    # Every collected step went to exactly one agent's buffer.
    np.testing.assert_array_equal(m.buffer_size.sum(1), [400] * g)
    assert np.all(np.isfinite(m.train.q_loss)) and np.all(m.eval.stage_fraction[:, 0] == 1.0)
    # Training episodes (tiny: 100 steps, 2 envs, so 2 end per epoch) all start in stage 1; a success ended in
    # the last stage.
    assert np.all(m.train_episodes == 2) and np.all(m.train_stage_fraction[:, 0] == 1.0)
    assert np.all(m.train_stage_fraction[:, 1] >= m.train_success)
    # The env's other metrics at the episodes' end (the maze's pocket), a fraction of the episodes.
    assert set(m.eval.end_metrics) == {"pocket"} and m.eval.end_metrics["pocket"].shape == (g,)
    assert np.all((m.eval.end_metrics["pocket"] >= 0) & (m.eval.end_metrics["pocket"] <= 1))


def test_state_keeps_its_avals_across_an_epoch(grid_run):
    """Shape, dtype and weak type of every state leaf survive train_step, so epoch 2 reuses epoch 1's program."""
    trainer, _ = grid_run
    eta, seed = GRID.grid_arrays()
    state = trainer.init(jnp.asarray(seed))
    aval = lambda tree: jax.tree.map(lambda x: (x.shape, x.dtype, x.weak_type), tree)
    before = aval(state)
    after, _ = trainer.train_step(state, jnp.asarray(eta))
    assert aval(after) == before


@pytest.mark.parametrize("algo", ["naive", "sac"])
def test_baseline_state_keeps_its_shapes_across_an_epoch(algo):
    """SAC's one agent over both stages included: a leaf that changes shape after the first epoch compiles the
    epoch twice and makes every checkpoint unreadable by the run that wrote it."""
    config = make_config("tiny", rooms=2, algo=algo, total_steps=400)
    trainer = make_train(config, make_env(config))
    state = jax.eval_shape(trainer.init, jnp.int32(0))
    after, _ = jax.eval_shape(trainer.train_step, state, jnp.asarray(config.grid_arrays()[0][0]))
    shapes = lambda tree: jax.tree.map(lambda x: (x.shape, x.dtype), tree)
    assert shapes(after) == shapes(state)


def test_same_seed_is_identical(grid_run):
    trainer, (state, _) = grid_run
    again, _ = _train(GRID, trainer, 2)
    for a, b in zip(jax.tree.leaves(state.agents), jax.tree.leaves(again.agents)):
        np.testing.assert_array_equal(a, b)


def test_grid_member_equals_the_run_alone(grid_run):
    _, (state, history) = grid_run
    alone = GRID.replace(etas=((0.9,),), seeds=(1,))
    solo_state, solo_history = _train(alone, make_grid_train(alone, make_env(alone)), 2)
    member = 3  # (eta 0.9, seed 1): ratios outermost
    assert GRID.members[member] == alone.members[0]
    for a, b in zip(jax.tree.leaves(state.agents), jax.tree.leaves(solo_state.agents)):
        np.testing.assert_allclose(a[member], b[0], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(history[-1].train.q_loss[member], solo_history[-1].train.q_loss[0], rtol=1e-4)
    np.testing.assert_array_equal(state.buffer.size[member], solo_state.buffer.size[0])


def test_vmapped_members_equal_members_one_at_a_time(grid_run):
    trainer, (state, history) = grid_run
    assert trainer.members_at_once in (1, GRID.grid_size)  # the CPU default for tiny nets: all four on ≥ 2 cores
    one_at_a_time = make_grid_train(GRID, make_env(GRID), members_at_once=1)
    assert one_at_a_time.members_at_once == 1
    o_state, o_history = _train(GRID, one_at_a_time, 2)
    for a, b in zip(jax.tree.leaves(state.agents), jax.tree.leaves(o_state.agents)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(history[-1].train.q_loss, o_history[-1].train.q_loss, rtol=1e-4)
    with pytest.raises(ConfigError, match="^members_at_once:"):
        make_grid_train(GRID, make_env(GRID), members_at_once=0)


def test_cpu_default_vmaps_members_while_their_critic_activations_stay_small():
    cpu, gpu = [types.SimpleNamespace(platform=p) for p in ("cpu", "gpu")]
    small = lambda **kw: make_config("small", **kw)  # [64, 64], batch 256: the yardstick's settings
    default = lambda config, cores=2.0, devices=(cpu,): default_members_at_once(list(devices), 32, config, cores)
    # CPU_VMAP_FLOATS holds 12 critic slots of [64, 64] at batch 256; CSAC has 2N − 1 slots per member
    assert critic_slots(small(algo="sac")) == 1 and critic_slots(small(algo="naive", rooms=3)) == 3
    assert [critic_slots(small(rooms=n)) for n in (2, 3, 4)] == [3, 5, 7]
    assert default(small(algo="sac")) == 12
    assert [default(small(rooms=n)) for n in (2, 3, 4)] == [4, 2, 1]
    assert default(small(rooms=3, hidden=(256, 256))) == 1  # never below one
    assert default(small(algo="sac"), cores=1.0) == 1  # a CPU split into a device per core: one at a time
    assert default(small(rooms=4), devices=(gpu,)) == 32  # accelerators: the whole local grid
    # the trainer rounds the default down to a divisor of the device's members (the tests' CPU: one device)
    sixteen = small(algo="sac", seeds=tuple(range(16)))
    expected = 8 if default_members_at_once(jax.devices()[:1], 16, sixteen) == 12 else 1
    assert make_grid_train(sixteen, make_env(sixteen), jax.devices()[:1]).members_at_once == expected


@pytest.mark.parametrize("algo", ["csac", "sac"])
def test_learning_on_a_two_stage_line(algo):
    """A point must cross two unit segments; random actions almost never make it in 50 steps."""
    config = make_config("tiny", algo=algo, seeds=(0, 1), total_steps=4000, train_loops_per_epoch=200,
                         hidden=(32, 32), batch_size=64, etas=((0.5,),))
    trainer = make_grid_train(config, Line(2, 50))
    _, history = _train(config, trainer, config.num_epochs)
    success = np.array([m.eval.success_rate for m in history])  # [epochs, grid]
    assert success[0].max() == 0.0
    assert success[-5:].mean() >= 0.9, success


def test_cli_writes_the_contract_files(tmp_path):
    out = tmp_path / "run"
    summary = main(["--preset", "tiny", "--rooms", "3", "--eta-per-agent", "0.1,1.0", "--seeds", "2",
                    "--out", str(out), "--no-progress"])
    config = json.loads((out / "config.json").read_text())
    assert config["grid"]["etas"] == [[0.1, 1.0]] and config["grid"]["seeds"] == [0, 1] and config["num_agents"] == 3
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2 * config["num_epochs"]
    for key in ("member", "seed", "eta", "epoch", "env_steps", "success_rate", "eval_return",
                "stage_reached_mean", "q_loss", "pi_loss", "alpha", "eta_star"):
        assert key in rows[0], key
    assert rows[0]["eta"] == [0.1, 1.0, 1.0] and len(rows[0]["q_loss"]) == 3 and rows[0]["eta_star"][2] is None
    assert set(rows[0]["eval_end"]) == {"pocket"} and len(rows[0]["train_stage_fraction"]) == 3
    saved = json.loads((out / "summary.json").read_text())
    assert [m["seed"] for m in saved["members"]] == [0, 1] == [m["seed"] for m in summary["members"]]
    assert all(0.0 <= m["final_success"] <= 1.0 for m in saved["members"])
    assert saved["q_bound"] == pytest.approx(1 / (1 - config["sac"]["gamma"]))
    for m in saved["members"]:
        mine = np.array([r["q_max"] for r in rows if r["member"] == m["member"]])  # [epochs, agents]
        np.testing.assert_allclose(m["q_peak"], mine.max(0))
        assert m["q_diverged_env_steps"] is None and mine.max() < 10 * saved["q_bound"]
    before = (out / "metrics.jsonl").read_bytes()
    with pytest.raises(ConfigError, match="^out:"):
        main(["--preset", "tiny", "--out", str(out), "--no-progress"])
    with pytest.raises(ConfigError, match="^members_at_once:"):
        main(["--preset", "tiny", "--members-at-once", "0", "--out", str(tmp_path / "never"), "--no-progress"])
    assert (out / "metrics.jsonl").read_bytes() == before and not (tmp_path / "never").exists()


def test_summary_flags_a_critic_above_ten_times_the_value_its_rewards_allow():
    from ccp_jax import outputs

    config = make_config("tiny", rooms=2, etas=((0.5,),), seeds=(0, 1), gamma=0.9)  # value bound 10, limit 100
    q_max = {0: [[5.0, 3.0], [99.0, 4.0], [19.0, 2.0]],  # close to the limit, never above it
             1: [[5.0, 3.0], [250.0, 4.0], [30.0, 101.0]]}
    rows = [dict(member=m, epoch=e + 1, env_steps=100 * (e + 1), success_rate=0.0, eval_return=0.0, q_max=q)
            for m, qs in q_max.items() for e, q in enumerate(qs)]
    summary = outputs.summarise(config, rows)
    assert summary["q_bound"] == pytest.approx(10.0)
    healthy, diverged = summary["members"]
    assert healthy["q_peak"] == [99.0, 4.0] and healthy["q_diverged_env_steps"] is None
    assert diverged["q_peak"] == [250.0, 101.0] and diverged["q_diverged_env_steps"] == 200  # the first epoch above
    warnings = [line for line in outputs.summary_table(summary).splitlines() if line.startswith("warning")]
    assert warnings == ["warning: member 1 (seed 1) diverged at 200 env steps: agent 0's critic reached 250, "
                        "above 100 (10 x the 10 its rewards allow); its diverged updates are discarded, so it keeps "
                        "its last healthy parameters while the grid trains on (per epoch: frozen, q_max, q_loss in "
                        "metrics.jsonl)"]
    assert (healthy["diverged_env_steps"], diverged["diverged_env_steps"]) == (None, 200)
    assert outputs.critic_peaks([dict(env_steps=5, q_max=[1.0, float("nan")])], 100.0)["q_diverged_env_steps"] == 5
    assert outputs.critic_peaks([dict(env_steps=5)], 100.0) == {"q_peak": None, "q_diverged_env_steps": None}  # TP


def test_a_runaway_actor_is_flagged_by_the_critic_loss_its_targets_drive():
    """`--actor-lr 1e6`: log π reaches 1e5, so the targets' −α log π and the critic loss explode while the critic's
    own values stay small; q_max alone never flagged it."""
    from ccp_jax import outputs

    healthy = dict(env_steps=100, q_max=[9.0, 3.0], q_loss=[0.5, 0.1], pi_loss=[-3.0, -2.0], alpha=[0.2, 0.2],
                   log_prob=[-1.0, 0.5])
    assert outputs.divergence(healthy, bound=20.0) is None
    assert outputs.divergence({**healthy, "q_loss": [0.5, 4.7e11]}, bound=20.0) == \
        "agent 1's critic loss reached 4.7e+11, above 160,000"
    assert outputs.divergence({**healthy, "q_loss": [159_999.0, 0.1]}, bound=20.0) is None  # (2 x 10 x 20)^2
    assert outputs.divergence({**healthy, "log_prob": [None, 0.5]}, bound=20.0) == "agent 0's log_prob is not finite"
    assert outputs.divergence({**healthy, "pi_loss": [1.0, math.inf]}, bound=20.0) == \
        "agent 1's pi_loss is not finite"
    assert outputs.divergence(dict(env_steps=5, success_rate=0.0), bound=20.0) is None  # TP rows: no learner values
    rows = [healthy, {**healthy, "env_steps": 200, "q_loss": [1e9, 0.1]}, {**healthy, "env_steps": 300}]
    assert outputs.first_divergence(rows, 20.0) == {"diverged_env_steps": 200, "frozen_epochs": 0,
                                                    "diverged": "agent 0's critic loss reached 1e+09, above 160,000"}


def test_a_member_that_diverges_is_reported_while_training(tmp_path, capsys):
    from ccp_jax.train import main

    summary = main(["--preset", "tiny", "--actor-lr", "1e6", "--no-progress", "--no-tensorboard",
                    "--out", str(tmp_path / "run")])
    assert summary["members"][0]["diverged_env_steps"] == 200
    assert summary["members"][0]["frozen_epochs"] == 2  # every epoch's updates discarded
    out = capsys.readouterr().out
    assert out.count("warning: member 0 (seed 0) diverged at 200 env steps") == 2  # as it happened, and at the end


def test_a_diverged_epoch_is_discarded_inside_the_program():
    """The member keeps the parameters and optimiser states it had before the epoch; a healthy one moves on."""
    for actor_lr, frozen in ((1e6, True), (3e-4, False)):
        config = make_config("tiny", actor_lr=actor_lr, seeds=(0,))
        trainer = make_train(config, make_env(config))
        state = trainer.init(jnp.int32(0))
        new, metrics = jax.jit(trainer.train_step)(state, jnp.array([0.1, 1.0], jnp.float32))
        assert bool(metrics.frozen) == frozen
        same = [bool(jnp.array_equal(a, b)) for a, b in zip(jax.tree.leaves(state.agents), jax.tree.leaves(new.agents))]
        assert all(same) if frozen else not all(same)
        assert int(new.env_steps) == 200 and int(new.epoch) == 1  # collection and the epoch count go on


def test_every_hyperparameter_reaches_the_config_from_the_cli():
    from ccp_jax.train import config_from_args, parse_args

    args = parse_args(["--preset", "tiny", "--tau", "0.01", "--actor-lr", "1e-3", "--critic-lr", "2e-3",
                       "--alpha-lr", "3e-3", "--start-steps", "50", "--normalise-last", "True",
                       "--eta-auto-range", "0.2", "0.8", "--next-action", "acting", "--normaliser", "ema",
                       "--train-cycles-per-epoch", "10", "--network-init", "rlkit", "--initial-alpha", "0.05",
                       "--coop-scale", "own", "--eta-auto-next-weight", "4"])
    config = config_from_args(args)
    assert (config.sac.tau, config.sac.actor_lr, config.sac.critic_lr, config.sac.alpha_lr) == (0.01, 1e-3, 2e-3, 3e-3)
    assert (config.budget.start_steps, config.ablations.normalise_last, config.ccp.eta_auto_range) == (50, True, (0.2, 0.8))
    assert (config.ablations.next_action, config.ablations.normaliser, config.ablations.train_cycles_per_epoch) == ("acting", "ema", 10)
    assert (config.ablations.network_init, config.sac.initial_alpha, config.ablations.coop_scale) == ("rlkit", 0.05, "own")
    assert config.ablations.eta_auto_next_weight == 4.0
    with pytest.raises(ConfigError, match="^eta_auto_next_weight:"):
        config_from_args(parse_args(["--preset", "tiny", "--eta-auto-next-weight", "0"]))
    with pytest.raises(ConfigError, match="^eta_auto_range:"):
        config_from_args(parse_args(["--preset", "tiny", "--eta-auto-range", "0.9", "0.1"]))


@pytest.mark.parametrize("algo", ["naive", "sac"])
def test_baselines_run_through_the_cli(tmp_path, algo):
    summary = main(["--preset", "tiny", "--algo", algo, "--out", str(tmp_path / algo), "--no-progress"])
    assert summary["members"][0]["algo"] == algo and summary["members"][0]["env_steps"] == 400


@pytest.mark.parametrize("cycles, updates", [(1, 20), (10, 18)])
def test_train_cycles_interleave_collection_and_updates(cycles, updates):
    """tiny: 200 steps (2 envs) and 20 loops per epoch, batch 32. In 10 cycles of 20 steps and 2 loops,
    agent 0's buffer holds 20 transitions after cycle 1 (not ready) and 40 from cycle 2: 9 × 2 updates."""
    import optax

    config = make_config("tiny", rooms=2, seeds=(0,), start_steps=0, train_cycles_per_epoch=cycles)
    trainer = make_grid_train(config, make_env(config))
    state, (m,) = _train(config, trainer, 1)
    assert m.buffer_size[0, 0] == 200 and m.env_steps[0] == 200  # every step in room 1, all collected
    count = optax.tree_utils.tree_get(state.agents.actor_opt, "count")
    assert count[0, 0] == updates
    assert m.train_episodes[0] >= 2  # episode stats summed over the cycles (tiny: 100-step episodes, 2 envs)


def test_train_cycles_must_divide_the_epoch():
    make_config("tiny", train_cycles_per_epoch=20)  # divides 100 vectorised steps and 20 loops
    for cycles in (0, 3, 25, 100):  # 25 and 100 divide the steps but not the loops
        with pytest.raises(ConfigError, match="^train_cycles_per_epoch:"):
            make_config("tiny", train_cycles_per_epoch=cycles)


def test_the_epoch_compiles_with_fusion_emitters_on_unless_the_env_runs_mjx():
    from envs_mjx import cpu_compiler_options
    from envs_mjx.maze import Maze

    class MjxMaze(Maze):
        @property
        def backend(self) -> str:
            return "mjx"

    on = {"xla_cpu_use_fusion_emitters": True}
    assert cpu_compiler_options(Maze(rooms=2)) == on
    assert cpu_compiler_options(MjxMaze(rooms=2)) == {}
    assert cpu_compiler_options(object()) == {}  # backend unknown: treated as MJX
    config = make_config("tiny", rooms=2)
    assert make_grid_train(config, Maze(rooms=2)).compiler_options == on
    assert make_grid_train(config, MjxMaze(rooms=2)).compiler_options == {}


def test_env_is_traced_once_per_call_kind_on_one_device():
    """Init, auto-reset and evaluation share one trace of `reset`, collection and evaluation one of `step`."""
    from envs_mjx.maze import Maze

    traced = {"reset": 0, "step": 0}

    class Counting(Maze):
        def reset(self, rng):
            traced["reset"] += 1
            return super().reset(rng)

        def step(self, state, action):
            traced["step"] += 1
            return super().step(state, action)

    config = make_config("tiny", rooms=2)
    trainer = make_grid_train(config, Counting(rooms=2, episode_length=config.task.max_episode_steps),
                              devices=jax.devices()[:1])
    eta, seeds = config.grid_arrays()
    state = trainer.abstract_state(seeds)
    trainer._step.trace(state, trainer._pad(eta))  # the epoch's program, traced but not compiled
    assert traced == {"reset": 1, "step": 1}


def test_outcome_rule_moves_eta_against_hand_values():
    from ccp_jax.eta import outcome_eta

    def move(eta, stages, successes, gate, rate=0.1, bounds=(0.05, 0.95)):
        return np.asarray(outcome_eta(jnp.asarray(eta, jnp.float32), jnp.asarray(stages, jnp.float32),
                                      jnp.float32(successes), rate, bounds, jnp.asarray(gate)))

    # 10 ended episodes: 6 reached stage 1, 2 stage 2, 1 succeeded. Failed in stage 0 / 1 / 2: 4 / 4 / 1.
    # Both terms before the successor's first success, but not below the middle (0.5) then; after it only the
    # downward one.
    np.testing.assert_allclose(move([0.5, 0.5, 0.5], [10, 6, 2], 1, [False, True, False]),
                               [0.5 + 0.1 * (4 - 4) / 10, 0.5 - 0.1 * 1 / 6, 0.5 + 0.1 * 1 / 2], rtol=1e-6)
    # 4 rooms: the third agent passes its room every time into a successor that never succeeded: from 0.95
    # back towards even weighting, held there; with the gate open the same episodes take it to the floor.
    np.testing.assert_allclose(move([0.95, 1.0], [5, 5], 0, [False, False]), [0.85, 0.95], rtol=1e-6)
    np.testing.assert_allclose(move([0.52, 1.0], [5, 5], 0, [False, False]), [0.5, 0.95], rtol=1e-6)
    np.testing.assert_allclose(move([0.1, 1.0], [5, 5], 0, [True, False]), [0.05, 0.95], rtol=1e-6)
    # Every episode hands over into a stage it then fails in (the maze's pocket), gate open: the first ratio falls.
    np.testing.assert_allclose(move([0.5, 1.0], [5, 5], 0, [True, False]), [0.4, 0.95], rtol=1e-6)
    # The agents no episode reached keep their ratios; nothing ended: nothing moves; all succeed: nothing moves.
    np.testing.assert_allclose(move([0.9, 0.3, 0.7], [3, 0, 0], 0, [True] * 3), [0.9, 0.3, 0.7], rtol=1e-6)
    np.testing.assert_allclose(move([0.2, 1.0], [0, 0], 0, [True, False]), [0.2, 0.95], rtol=1e-6)
    np.testing.assert_allclose(move([0.5, 0.5], [4, 4], 4, [True, True]), [0.5, 0.5], rtol=1e-6)


def test_successor_succeeded_looks_two_stages_ahead():
    from ccp_jax.eta import successor_succeeded

    def check(stages, successes, agents=None):
        return np.asarray(successor_succeeded(jnp.asarray(stages, jnp.float32), jnp.float32(successes),
                                              agents or len(stages))).tolist()

    assert check([10, 6, 2], 1) == [True, True, False]  # stage 2 reached (agent 0's), a success (agent 1's)
    assert check([10, 6, 0], 0) == [False, False, False]
    assert check([5, 2], 0) == [False, False] and check([5, 2], 1) == [True, False]
    assert check([5, 2], 1, agents=1) == [False]  # SAC: one agent over both stages, no successor


def test_outcome_rule_trains_auto_members_at_its_ratios_epoch_by_epoch():
    """An "auto" member trains epoch k + 1 at `outcome_eta` of epoch k's training episodes (under the gate of
    every epoch's successes so far); a numeric member beside it keeps its ratio."""
    from ccp_jax.eta import outcome_eta, successor_succeeded

    rule = "trusted"
    config = make_config("tiny", rooms=2, etas=(("auto",), (0.3,)), seeds=(0,), total_steps=600,
                         eta_auto_rule=rule, eta_auto_rate=0.2)
    state, history = _train(config, make_grid_train(config, make_env(config)), 3)
    used = np.array([m.train.eta_used[:, 0] for m in history])  # [epochs, members]
    np.testing.assert_allclose(used[:, 1], 0.3, rtol=1e-6)
    expected, gate = [0.5], jnp.zeros((2,), bool)
    for m in history:
        stages = jnp.asarray(m.train_stage_fraction[0] * m.train_episodes[0])
        successes = jnp.asarray(m.train_success[0] * m.train_episodes[0])
        gate = gate | successor_succeeded(stages, successes, 2)
        expected.append(float(outcome_eta(jnp.full((2,), expected[-1]), stages, successes, 0.2,
                                          config.ccp.eta_auto_range, gate=gate)[0]))
    np.testing.assert_allclose(used[:, 0], expected[:3], rtol=1e-5)
    np.testing.assert_allclose(state.eta_auto[0, 0], expected[3], rtol=1e-5)
    np.testing.assert_array_equal(state.successor_succeeded[0], gate)
    assert len(set(np.round(expected, 4))) > 1, "the tiny maze's episodes should move the ratio"


def test_outcome_rule_fields_are_validated_and_reach_the_config_from_the_cli():
    from ccp_jax.train import config_from_args, parse_args

    config = config_from_args(parse_args(["--preset", "tiny", "--eta", "auto", "--eta-auto-rule", "trusted",
                                          "--eta-auto-rate", "0.1"]))
    assert (config.ccp.eta_auto_rule, config.ccp.eta_auto_rate) == ("trusted", 0.1)
    assert make_config("tiny").ccp.eta_auto_rule == "ranges"
    for field, value in (("eta_auto_rule", "returns"), ("eta_auto_rule", "outcomes"), ("eta_auto_rule", "gated"),
                         ("eta_auto_rate", 0.0),
                         ("eta_auto_rate", 1.5), ("eta_auto_rate", float("nan"))):
        with pytest.raises(ConfigError, match=f"^{field}:"):
            make_config("tiny", **{field: value})
    for retired in ("eta_auto_up_rate", "eta_auto_floor_step"):  # retired (docs/design.md#retired-settings)
        with pytest.raises(ConfigError, match=f"^{retired}: not a configuration field"):
            make_config("tiny", **{retired: 0.0})
        with pytest.raises(SystemExit):
            parse_args(["--preset", "tiny", "--" + retired.replace("_", "-"), "0"])
