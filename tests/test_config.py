"""Bad input fails fast, naming the field; presets and the grid resolve as documented."""
import pytest

from ccp_jax.config import ConfigError, make_config
from ccp_jax.train import Args, config_from_args


@pytest.mark.parametrize("overrides, field", [
    (dict(env="mujoco_soccer"), "env"),
    (dict(algo="ppo"), "algo"),
    (dict(rooms=1), "rooms"),
    (dict(etas=((1.5,),)), "eta"),
    (dict(etas=((-0.1,),)), "eta"),
    (dict(rooms=3, etas=((0.1, 0.2, 0.3, 0.4),)), "eta_per_agent"),
    (dict(rooms=3, etas=((0.1, 0.2, 0.3),)), "eta_per_agent"),  # N values only with normalise_last
    (dict(batch_size=512, buffer_size=256), "batch_size"),
    (dict(batch_size=0), "batch_size"),
    (dict(buffer_size=-5), "buffer_size"),
    (dict(steps_per_epoch=0), "steps_per_epoch"),
    (dict(num_envs=3), "num_envs"),  # must divide steps_per_epoch
    (dict(total_steps=10), "total_steps"),
    (dict(gamma=1.0), "gamma"),
    (dict(hidden=(64, 0)), "hidden"),
    (dict(seeds=(1, 1)), "seeds"),
    (dict(tanh_log_prob="torch"), "tanh_log_prob"),
    (dict(network_init="torch"), "network_init"),
    (dict(coop_scale="reward"), "coop_scale"),
    (dict(train_cycles_per_epoch=3), "train_cycles_per_epoch"),  # tiny: 100 vectorised steps, 20 loops
    (dict(target_entropy=float("nan")), "target_entropy"),
    (dict(initial_alpha=0.0), "initial_alpha"),
    (dict(initial_alpha=float("inf")), "initial_alpha"),
    (dict(no_such_field=1), "no_such_field"),
    (dict(env="peg", maze_slide=False), "maze_slide"),  # a maze option on another env
    (dict(env="peg", maze_reverse=True), "maze_reverse"),
    (dict(maze_reverse="no"), "maze_reverse"),
])
def test_bad_config_names_the_field(overrides, field):
    with pytest.raises(ConfigError) as err:
        make_config("tiny", **overrides)
    assert err.value.field == field
    assert str(err.value).startswith(field + ":")


def test_unknown_preset():
    with pytest.raises(ConfigError, match="^preset:"):
        make_config("huge")


def test_paper_preset_matches_the_paper():
    c = make_config("paper")
    assert (c.gamma, c.buffer_size, c.batch_size, c.max_episode_steps, c.tau) == (0.95, 1_000_000, 256, 1000, 0.005)
    assert (c.steps_per_epoch, c.train_loops_per_epoch, c.hidden, c.start_steps) == (5000, 1000, (256, 256), 1000)
    assert c.num_epochs == 600 and c.eval_episodes == 10 and c.absorbing_success


def test_eta_vectors_and_grid_order():
    c = make_config("tiny", rooms=3, etas=((0.1,), (0.1, 1.0)), seeds=(4, 5))
    eta, seed = c.grid_arrays()
    assert eta.shape == (4, 3) and seed.tolist() == [4, 5, 4, 5]
    assert eta[0].tolist() == pytest.approx([0.1, 0.1, 1.0])  # shared ratio, last agent 1
    assert eta[2].tolist() == pytest.approx([0.1, 1.0, 1.0])  # per-agent vector
    sac = make_config("tiny", rooms=3, algo="sac")
    assert sac.num_agents == 1 and sac.grid_arrays()[0].shape == (1, 1)


def test_cli_arguments_resolve():
    c = config_from_args(Args(rooms=3, eta_per_agent=("0.1,1.0", "0.5,0.5"), seeds=2, preset="tiny"))
    assert c.etas == ((0.1, 1.0), (0.5, 0.5)) and c.seeds == (0, 1) and c.grid_size == 4
    assert config_from_args(Args(target_entropy=-0.5, preset="tiny")).target_entropy == -0.5
    robot = config_from_args(Args(maze_reverse=True, maze_slide=False, preset="tiny"))
    from ccp_jax.envs import make_env
    assert (make_env(robot).geometry.reverse, make_env(robot).geometry.slide) == (True, False)
    assert (make_env(make_config("tiny")).geometry.reverse, make_env(make_config("tiny")).geometry.slide) == (False, True)
    base = make_config("tiny")
    other = base.replace(total_steps=800, normaliser="floor", gamma=0.9)
    assert base.differing(other) == ["total_steps", "gamma", "normaliser"]  # declaration order
    assert base.differing(other, ignore=("total_steps",)) == ["gamma", "normaliser"] and base.differing(base) == []
    with pytest.raises(ConfigError, match="^eta_per_agent:"):
        config_from_args(Args(rooms=3, eta_per_agent=("0.1;1.0",), preset="tiny"))
    with pytest.raises(ConfigError, match="^eta_per_agent:"):
        config_from_args(Args(rooms=4, eta_per_agent=("0.1,1.0",), preset="tiny"))
    with pytest.raises(ConfigError, match="^eta_per_agent: ratio vector 0.1 has 1 value; 3 agents need 2 values"):
        config_from_args(Args(rooms=3, eta_per_agent=("0.1", "0.5"), preset="tiny"))  # a space for a comma
    assert config_from_args(Args(rooms=2, eta_per_agent=("0.1",), preset="tiny")).etas == ((0.1,),)
    with pytest.raises(ConfigError, match="^rooms: --rooms sets the maze's number of rooms; env 'peg'"):
        config_from_args(Args(env="peg", rooms=3, preset="tiny"))
    assert config_from_args(Args(env="peg", preset="tiny")).num_stages == 2
    with pytest.raises(ConfigError, match="^eta: ratios must be distinct"):
        config_from_args(Args(eta=("0.1", "0.10"), preset="tiny"))
    with pytest.raises(ConfigError, match="^eta: ratios must be distinct"):
        make_config("tiny", rooms=3, etas=((0.1,), (0.1, 0.1)))  # the same per-agent vector
    with pytest.raises(ConfigError, match="^seeds:"):
        config_from_args(Args(seeds=0, preset="tiny"))
    with pytest.raises(ConfigError, match="^eta:"):
        config_from_args(Args(eta=(0.1,), eta_per_agent=("0.1",), preset="tiny"))


def test_compile_cache_keeps_the_users_folder_else_uses_xdg_cache(tmp_path, monkeypatch):
    import jax

    from ccp_jax.train import enable_compile_cache

    before = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
        assert enable_compile_cache() == tmp_path / "mine"  # a user's (or the test suite's) choice is kept
        jax.config.update("jax_compilation_cache_dir", None)
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
        assert enable_compile_cache() == tmp_path / "xdg" / "ccp-jax" / "xla"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "xdg" / "ccp-jax" / "xla")
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
    assert Args().compile_cache  # on by default in the CLI


def test_a_config_json_from_before_the_kinematics_fields_reads_as_the_robot_it_trained():
    """Runs of sessions 1-27 wrote no maze_reverse / maze_slide: they drove backwards and stopped at walls."""
    from ccp_jax.config import Config
    old_maze = {k: v for k, v in make_config("tiny").to_dict().items() if k not in ("maze_reverse", "maze_slide")}
    legacy = Config.from_dict(old_maze)
    assert (legacy.maze_reverse, legacy.maze_slide) == (True, False)
    assert legacy.differing(make_config("tiny")) == ["maze_reverse", "maze_slide"]  # so train --resume keeps them
    written = Config.from_dict(make_config("tiny").to_dict())  # a file that records them keeps its values
    assert (written.maze_reverse, written.maze_slide) == (False, True)
    old_peg = {k: v for k, v in make_config("tiny", env="peg").to_dict().items() if k not in ("maze_reverse", "maze_slide")}
    assert Config.from_dict(old_peg) == make_config("tiny", env="peg")  # other envs have no kinematics to recall


def test_a_folder_without_a_readable_run_is_named_by_the_argument_that_gave_it(tmp_path, capsys):
    from ccp_jax import evaluate, outputs, plot

    with pytest.raises(ConfigError, match=f"^run_dir: {tmp_path} holds no run"):
        outputs.read_config(tmp_path)
    with pytest.raises(SystemExit):
        evaluate.main([str(tmp_path)])
    with pytest.raises(SystemExit):
        plot.main([str(tmp_path)])
    assert capsys.readouterr().err.splitlines() == [f"error: run_dir: {tmp_path} holds no run (no config.json)"] * 2
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match="^resume: .*config.json is unreadable"):
        outputs.read_config(tmp_path, field="resume")


def test_algorithms_without_cooperation_refuse_ratios():
    assert config_from_args(Args(algo="naive", rooms=3, preset="tiny")).algo == "naive"  # no --eta: accepted
    with pytest.raises(ConfigError, match="^eta: --algo naive trains every agent"):
        config_from_args(Args(algo="naive", eta=("0.3",), preset="tiny"))  # one ratio: it would be ignored
    with pytest.raises(ConfigError, match="^eta: --algo sac trains every agent on its own critic alone"):
        config_from_args(Args(algo="sac", eta=("0.1", "0.5"), preset="tiny"))
    with pytest.raises(ConfigError, match="^eta: --algo naive .* a grid of ratios would train identical runs"):
        make_config("tiny", algo="naive", etas=((0.1,), (0.5,)))


def test_a_resume_that_changes_a_field_names_it_even_where_the_saved_ratios_no_longer_fit(tmp_path):
    import json

    from ccp_jax.train import resume_config

    saved = make_config("tiny", rooms=3, etas=((0.1, 0.5),))
    (tmp_path / "config.json").write_text(json.dumps(saved.to_dict()))
    for args, field in ((Args(resume=tmp_path, rooms=4), "rooms"), (Args(resume=tmp_path, algo="naive"), "algo"),
                        (Args(resume=tmp_path, env="peg"), "env")):
        with pytest.raises(ConfigError, match=f"^{field}: the run in {tmp_path} was trained with"):
            resume_config(args)
    assert resume_config(Args(resume=tmp_path, total_steps=2 * saved.total_steps)).total_steps == 2 * saved.total_steps
