"""Bad input fails fast, naming the field; presets and the grid resolve as documented."""
import json
import math

import pytest

from ccp_jax.config import ConfigError, make_config
from ccp_jax.train import Args, config_from_args, parse_args


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
    (dict(env="peg", peg_model="gripper"), "peg_model"),
    (dict(peg_model="hand"), "peg_model"),  # a peg option on another env (tiny's maze)
    (dict(env="peg", peg_physics="warp"), "peg_physics"),
    (dict(peg_physics="c"), "peg_physics"),  # a peg option on another env (tiny's maze)
    (dict(peg_grip_held=True), "peg_grip_held"),
    (dict(env="peg", peg_grip_held="yes"), "peg_grip_held"),
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
    assert (c.sac.gamma, c.sac.buffer_size, c.sac.batch_size, c.task.max_episode_steps, c.sac.tau) == (0.95, 1_000_000, 256, 1000, 0.005)
    assert (c.budget.steps_per_epoch, c.budget.train_loops_per_epoch, c.sac.hidden, c.budget.start_steps) == (5000, 1000, (256, 256), 1000)
    assert c.num_epochs == 600 and c.budget.eval_episodes == 10 and c.ccp.absorbing_success


def test_eta_vectors_and_grid_order():
    c = make_config("tiny", rooms=3, etas=((0.1,), (0.1, 1.0)), seeds=(4, 5))
    eta, seed = c.grid_arrays()
    assert eta.shape == (4, 3) and seed.tolist() == [4, 5, 4, 5]
    assert eta[0].tolist() == pytest.approx([0.1, 0.1, 1.0])  # shared ratio, last agent 1
    assert eta[2].tolist() == pytest.approx([0.1, 1.0, 1.0])  # per-agent vector
    sac = make_config("tiny", rooms=3, algo="sac")
    assert sac.num_agents == 1 and sac.grid_arrays()[0].shape == (1, 1)


def test_cli_arguments_resolve():
    c = config_from_args(parse_args(["--rooms", "3", "--eta-per-agent", "0.1,1.0", "0.5,0.5", "--seeds", "2", "--preset", "tiny"]))
    assert c.grid.etas == ((0.1, 1.0), (0.5, 0.5)) and c.grid.seeds == (0, 1) and c.grid_size == 4
    assert config_from_args(parse_args(["--target-entropy", "-0.5", "--preset", "tiny"])).sac.target_entropy == -0.5
    robot = config_from_args(parse_args(["--maze-reverse", "True", "--maze-slide", "False", "--preset", "tiny"]))
    from ccp_jax.envs import make_env
    assert (make_env(robot).geometry.reverse, make_env(robot).geometry.slide) == (True, False)
    assert (make_env(make_config("tiny")).geometry.reverse, make_env(make_config("tiny")).geometry.slide) == (False, True)
    base = make_config("tiny")
    other = base.replace(total_steps=800, normaliser="floor", gamma=0.9)
    assert base.differing(other) == ["total_steps", "gamma", "normaliser"]  # declaration order
    assert base.differing(other, ignore=("total_steps",)) == ["gamma", "normaliser"] and base.differing(base) == []
    with pytest.raises(ConfigError, match="^eta_per_agent:"):
        config_from_args(parse_args(["--rooms", "3", "--eta-per-agent", "0.1;1.0", "--preset", "tiny"]))
    with pytest.raises(ConfigError, match="^eta_per_agent:"):
        config_from_args(parse_args(["--rooms", "4", "--eta-per-agent", "0.1,1.0", "--preset", "tiny"]))
    with pytest.raises(ConfigError, match="^eta_per_agent: ratio vector 0.1 has 1 value; 3 agents need 2 values"):
        config_from_args(parse_args(["--rooms", "3", "--eta-per-agent", "0.1", "0.5", "--preset", "tiny"]))  # a space for a comma
    assert config_from_args(parse_args(["--rooms", "2", "--eta-per-agent", "0.1", "--preset", "tiny"])).grid.etas == ((0.1,),)
    with pytest.raises(ConfigError, match="^rooms: --rooms sets the maze's number of rooms; env 'peg'"):
        config_from_args(parse_args(["--env", "peg", "--rooms", "3", "--preset", "tiny"]))
    assert config_from_args(parse_args(["--env", "peg", "--preset", "tiny"])).num_stages == 2
    with pytest.raises(ConfigError, match="^eta: ratios must be distinct"):
        config_from_args(parse_args(["--eta", "0.1", "0.10", "--preset", "tiny"]))
    with pytest.raises(ConfigError, match="^eta: ratios must be distinct"):
        make_config("tiny", rooms=3, etas=((0.1,), (0.1, 0.1)))  # the same per-agent vector
    with pytest.raises(ConfigError, match="^seeds:"):
        config_from_args(parse_args(["--seeds", "0", "--preset", "tiny"]))
    with pytest.raises(ConfigError, match="^eta:"):
        config_from_args(parse_args(["--eta", "0.1", "--eta-per-agent", "0.1", "--preset", "tiny"]))


def test_host_cpu_tag_names_the_cpu_model_and_features(monkeypatch):
    import platform

    from ccp_jax.devices import host_cpu_tag

    tag = host_cpu_tag()
    assert len(tag) == 12 and int(tag, 16) >= 0 and host_cpu_tag() == tag
    monkeypatch.setattr(platform, "machine", lambda: "riscv128")  # another machine, another cache folder
    assert host_cpu_tag() != tag


def test_compile_cache_keeps_the_users_folder_else_uses_xdg_cache(tmp_path, monkeypatch):
    import jax

    from ccp_jax.devices import host_cpu_tag
    from ccp_jax.train import enable_compile_cache

    before = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
        assert enable_compile_cache() == tmp_path / "mine"  # a user's (or the test suite's) choice is kept
        jax.config.update("jax_compilation_cache_dir", None)
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
        mine = tmp_path / "xdg" / "ccp-jax" / "xla" / host_cpu_tag()  # one folder per CPU model and features
        assert enable_compile_cache() == mine
        assert jax.config.jax_compilation_cache_dir == str(mine)
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
    assert Args().compile_cache  # on by default in the CLI


def test_a_config_json_from_before_the_kinematics_fields_reads_as_the_robot_it_trained():
    """Runs on the first robot wrote no maze_reverse / maze_slide: they drove backwards and stopped at walls."""
    from ccp_jax.config import Config
    old_maze = {k: v for k, v in make_config("tiny").flat().items() if k not in ("maze_reverse", "maze_slide")}
    legacy = Config.from_dict(old_maze)
    assert (legacy.ablations.maze_reverse, legacy.ablations.maze_slide) == (True, False)
    assert legacy.differing(make_config("tiny")) == ["maze_reverse", "maze_slide"]  # so train --resume keeps them
    written = Config.from_dict(make_config("tiny").to_dict())  # a file that records them keeps its values
    assert (written.ablations.maze_reverse, written.ablations.maze_slide) == (False, True)
    old_peg = {k: v for k, v in make_config("tiny", env="peg").flat().items() if k not in ("maze_reverse", "maze_slide")}
    assert Config.from_dict(old_peg) == make_config("tiny", env="peg")  # other envs have no kinematics to recall


def test_a_config_json_from_before_peg_model_reads_as_the_arm():
    """peg_model came with the hand variant; every run before it stepped the arm, in either config.json form."""
    from ccp_jax.config import Config

    arm, hand = make_config("tiny", env="peg"), make_config("tiny", env="peg", peg_model="hand")
    assert (arm.task.peg_model, hand.task.peg_model) == ("arm", "hand")
    nested = arm.to_dict()
    del nested["task"]["peg_model"]
    flat = {k: v for k, v in arm.flat().items() if k != "peg_model"}  # version 1: no "version" key
    for old in (nested, flat):
        assert Config.from_dict(old).task.peg_model == "arm"
    assert Config.from_dict(hand.to_dict()) == hand  # a file that records it keeps it


def test_a_run_with_a_retired_setting_reads_plots_and_compares_but_refuses_to_train(tmp_path):
    """docs/design.md#retired-settings: a removed setting at its old default reads as if absent; a retired value
    reads into Config.retired, which keeps the run apart from others and stops training and resume by name."""
    from ccp_jax import outputs, plot
    from ccp_jax.config import SECTION_OF, Config
    from ccp_jax.train import main as train_main

    current = make_config("tiny", etas=(("auto",),), eta_auto_rule="trusted")
    nested = current.to_dict()
    nested["ablations"].update(eta_auto_up_rate=None, eta_auto_floor_step=0.0)  # as every version-2 file wrote them
    assert Config.from_dict(nested) == current and not current.retired
    flat = {**current.flat(), "eta_auto_rule": "outcomes", "eta_auto_up_rate": 0.0}  # a version-1 file
    old = Config.from_dict(flat)
    assert old.retired == (("eta_auto_rule", "outcomes"), ("eta_auto_up_rate", 0.0))
    assert old.ccp.eta_auto_rule == "ranges"  # the section holds the default; the run's value is in `retired`
    assert old.differing(current) == ["eta_auto_rule", "retired"]
    assert Config.from_dict(json.loads(json.dumps(old.to_dict()))) == old
    floors = Config.from_dict({**nested, "ablations": {**nested["ablations"], "eta_auto_floor_step": 0.25}})
    assert floors.retired == (("eta_auto_floor_step", 0.25),) and floors.ccp.eta_auto_rule == "trusted"
    with pytest.raises(ConfigError, match="^eta_auto_rule: 'outcomes' is retired"):
        old.check_trainable()
    section = SECTION_OF["eta_auto_rule"]
    gated = Config.from_dict({**nested, section: {**nested[section], "eta_auto_rule": "gated"}})
    assert gated.retired == (("eta_auto_rule", "gated"),) and gated.ccp.eta_auto_rule == "ranges"
    with pytest.raises(ConfigError, match="^eta_auto_rule: 'gated' is retired"):
        gated.check_trainable()

    run = tmp_path / "old_run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(flat))
    row = {"epoch": 0, "env_steps": 200, "member": 0, "seed": 0, "eta": ["auto"], "algo": "csac",
           "success_rate": 0.5}
    (run / "metrics.jsonl").write_text(json.dumps(row) + "\n")
    assert outputs.read_config(run) == old
    [[series]] = plot.load_curves([run]).values()
    assert series[1].tolist() == [0.5]
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    with pytest.raises(ConfigError, match="^eta_auto_rule: 'outcomes' is retired"):
        train_main(["--resume", str(run)])
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before  # nothing written


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
    assert config_from_args(parse_args(["--algo", "naive", "--rooms", "3", "--preset", "tiny"])).algo == "naive"  # no --eta: accepted
    with pytest.raises(ConfigError, match="^eta: --algo naive trains every agent"):
        config_from_args(parse_args(["--algo", "naive", "--eta", "0.3", "--preset", "tiny"]))  # one ratio: it would be ignored
    with pytest.raises(ConfigError, match="^eta: --algo sac trains every agent on its own critic alone"):
        config_from_args(parse_args(["--algo", "sac", "--eta", "0.1", "0.5", "--preset", "tiny"]))
    with pytest.raises(ConfigError, match="^eta: --algo naive .* a grid of ratios would train identical runs"):
        make_config("tiny", algo="naive", etas=((0.1,), (0.5,)))


def test_a_resume_that_changes_a_field_names_it_even_where_the_saved_ratios_no_longer_fit(tmp_path):
    import json

    from ccp_jax.train import resume_config

    saved = make_config("tiny", rooms=3, etas=((0.1, 0.5),))
    (tmp_path / "config.json").write_text(json.dumps(saved.to_dict()))
    for argv, field in ((["--rooms", "4"], "rooms"), (["--algo", "naive"], "algo"), (["--env", "peg"], "env")):
        with pytest.raises(ConfigError, match=f"^{field}: the run in {tmp_path} was trained with"):
            resume_config(parse_args(["--resume", str(tmp_path)] + argv))
    longer = ["--resume", str(tmp_path), "--total-steps", str(2 * saved.budget.total_steps)]
    assert resume_config(parse_args(longer)).budget.total_steps == 2 * saved.budget.total_steps


def _tupled(x):
    return tuple(_tupled(v) for v in x) if isinstance(x, list) else x


def test_every_committed_config_json_reads_with_its_own_values():
    """Every config.json under experiments/results (each form ever written) migrates to the current form with the
    values it holds; a setting it lacks takes its default, a version-1 maze's kinematics LEGACY_MAZE's robot; a
    retired one is in `retired` unless it held a removed setting's old default."""
    from pathlib import Path

    from ccp_jax.config import LEGACY_MAZE, RETIRED_SETTINGS, RETIRED_VALUES, SECTION_OF, SECTIONS, Config

    files = sorted((Path(__file__).parent.parent / "experiments" / "results").glob("**/config.json"))
    assert len(files) > 100
    defaults = Config().flat()
    for path in files:
        written = json.loads(path.read_text())
        config = Config.from_dict(written)
        flat = config.flat()
        version = written.get("version", 1)  # 1: every setting at the top level; 2 on: nested by section
        held = written if version == 1 else {k: v for name in SECTIONS for k, v in written.get(name, {}).items()}
        settings = {k: _tupled(v) for k, v in held.items() if k in SECTION_OF}
        if version > 1 and "algo" in written:
            settings["algo"] = written["algo"]
        retired = {k: _tupled(v) for k, v in held.items()
                   if k in RETIRED_SETTINGS and v != RETIRED_SETTINGS[k][1] or v in RETIRED_VALUES.get(k, ())}
        assert dict(config.retired) == retired, path
        settings = {k: v for k, v in settings.items() if k not in retired}
        assert {k: flat[k] for k in settings} == settings, path
        for name in set(SECTION_OF) - set(settings) - set(retired):
            legacy = version == 1 and config.task.env == "maze" and name in LEGACY_MAZE
            assert flat[name] == (LEGACY_MAZE[name] if legacy else defaults[name]), (path, name)
        for name in ("num_stages", "num_agents", "num_epochs", "grid_size"):
            assert getattr(config, name) == written[name], (path, name)
        assert Config.from_dict(json.loads(json.dumps(config.to_dict()))) == config, path


def test_config_json_round_trips_and_refuses_what_it_cannot_read():
    import json

    from ccp_jax.config import VERSION, Config, migrate

    for config in (make_config("tiny"), make_config("paper", rooms=4, etas=((0.1, "auto", 0.5),), seeds=(3, 4)),
                   make_config("tiny", env="peg", algo="naive"), make_config("tiny", algo="tp", primitives="/p")):
        written = json.loads(json.dumps(config.to_dict()))
        assert written["version"] == VERSION and written["tp"]["primitives"] == config.tp.primitives
        assert Config.from_dict(written) == config and migrate(written) == migrate(migrate(written))
        flat = json.loads(json.dumps({**config.flat(), "num_stages": config.num_stages}))  # the older form
        assert Config.from_dict(flat) == config
    with pytest.raises(ConfigError, match="^version:"):
        Config.from_dict({**make_config("tiny").to_dict(), "version": VERSION + 1})
    with pytest.raises(TypeError, match="no setting 'gama'"):
        Config.from_dict({**make_config("tiny").to_dict(), "sac": {"gama": 0.9}})


def test_settings_are_read_by_flat_name_and_kept_in_sections():
    from ccp_jax.config import SECTION_OF, SECTIONS

    c = make_config("tiny", actor_lr=1e-3, tp_lr=2e-4, normaliser="floor")
    assert (c.sac.actor_lr, c.tp.tp_lr, c.ablations.normaliser) == (1e-3, 2e-4, "floor")
    assert c.replace(gamma=0.9).sac.gamma == 0.9 and c.replace(gamma=0.9).replace(sac=c.sac) == c
    assert list(c.flat()) == list(SECTION_OF) and set(SECTION_OF) - {"algo"} == {
        f for section in SECTIONS.values() for f in section.__dataclass_fields__}
    with pytest.raises(ConfigError, match="^gama: not a configuration field"):
        c.replace(gama=0.9)


def test_help_shows_the_core_flags_first_the_rest_by_section_and_docs_cli_md_is_it():
    import importlib.util
    from pathlib import Path

    script = Path(__file__).parent.parent / "docs" / "make_cli.py"
    spec = importlib.util.spec_from_file_location("make_cli", script)
    make_cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_cli)
    text = make_cli.help_text()
    assert make_cli.PAGE.read_text() == make_cli.HEADER + text + "\n```\n", "stale: run python docs/make_cli.py"
    boxes = [line.split(" options")[0].strip("╭─ ") for line in text.splitlines() if line.startswith("╭─")]
    assert boxes == ["", "budget", "sac", "ccp", "tp", "ablations", "devices"]
    first = text.split("budget options")[0]
    for flag in ("--env", "--rooms", "--algo", "--eta ", "--eta-per-agent", "--seeds", "--first-seed", "--preset",
                 "--total-steps", "--out", "--resume", "--checkpoint-every", "--progress", "--tensorboard",
                 "--wandb-project", "--eta-auto-rule"):
        assert flag in first, flag
    assert first.count("│ --") <= 25


def test_a_budget_of_part_of_an_epoch_is_refused_with_the_nearest_whole_ones():
    """--total-steps 250 with 200-step epochs would train one epoch (200 steps) without a word."""
    with pytest.raises(ConfigError, match=r"^total_steps: must be a whole number of epochs of 200 steps, got 250: "
                                          r"use 200 or 400$"):
        make_config("tiny", total_steps=250)
    assert make_config("tiny", total_steps=400).num_epochs == 2


@pytest.mark.parametrize("name, value", [("actor_lr", math.nan), ("critic_lr", math.inf), ("norm_floor", math.nan),
                                         ("initial_alpha", -math.inf), ("eta_auto_range", (0.0, math.nan))])
def test_non_finite_numbers_are_refused_by_name(name, value):
    """nan slips past `x <= 0` checks: `--actor-lr nan` used to train, every loss nan, and exit 0."""
    with pytest.raises(ConfigError, match=rf"^{name}: .*finite"):
        make_config("tiny", **{name: value})
