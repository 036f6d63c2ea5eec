"""Command line and Python entry point: train a whole grid of runs in one program.

    python -m ccp_jax.train --env maze --rooms 3 --algo csac --eta 0.1 0.5 0.9 --seeds 5 --out runs/x

The host loop below only logs, shows progress, saves and (with --video-every) films; each epoch of every
grid member is one call of the compiled, vmapped `train_step`.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":  # the CLI: MJX's CPU flag and quiet import, before the imports below load brax and MJX
    envs_mjx.configure_cpu()

import argparse
import ast
import dataclasses
import errno
import functools
import inspect
import json
import os
import sys
import textwrap
import time
import typing
from pathlib import Path
from typing import Annotated, Any, Mapping, Optional, Sequence

import jax
import numpy as np
import tyro
from jax.experimental import multihost_utils
from tqdm.auto import tqdm

from ccp_jax import checkpoint, loggers, outputs, video
from ccp_jax.devices import CpuDevices, grid_devices, host_cpu_tag, split_host_cpu
from ccp_jax.config import (PRESETS, SECTION_OF, SECTIONS, Config, ConfigError, PresetName, make_config,
                             preset_settings)
from ccp_jax.eta import EtaAutoRule, parse_eta, parse_eta_vector
from ccp_jax.envs import make_env, user_env
from ccp_jax.grid import check_members_at_once, make_grid_train
from ccp_jax.learner import make_networks
from ccp_jax.tp.primitives import primitives_config
from ccp_jax.tp.trainer import make_tp_grid


@dataclasses.dataclass(frozen=True)
class Hosts:
    """Devices and hosts: where the grid trains. None of these changes results beyond float rounding
    (docs/multi-device.md)."""

    cpu_devices: CpuDevices = "auto"
    """On a CPU: split it into this many XLA devices, so grid members train side by side (auto: the count that wastes least for this grid, of up to twice the cores, ccp_jax.devices.grid_devices: one run keeps the whole CPU as one device, 3 runs on 2 cores take 3; 1: the whole CPU as one device). A count set in $XLA_FLAGS wins."""
    members_at_once: Optional[int] = None
    """Grid members each device advances together (vmapped); the rest run one group after another in the same program. Default: all on GPU/TPU; on a CPU device of several cores as many as keep the stacked critic activations small (ccp_jax.devices.default_members_at_once: 12 [64, 64] SAC members, 4 2-agent or 2 3-agent CSAC members), on a CPU split into a device per core 1."""
    distributed: bool = False
    """Multi-host: call jax.distributed.initialize() first (every host runs the same command; see README)."""
    coordinator: Optional[str] = None
    """With --distributed: host0:port of the coordinator (auto-detected on SLURM, Open MPI, Kubernetes, Cloud TPU)."""
    num_processes: Optional[int] = None
    """With --distributed: the number of hosts (auto-detected where the coordinator is)."""
    process_id: Optional[int] = None
    """With --distributed: this host's index (auto-detected where the coordinator is)."""


@dataclasses.dataclass(frozen=True)
class Args:
    """Train CSAC (or a baseline) on a multi-stage task; every ratio × seed in one vmapped program.

    Options left unset take the preset's value (or, with --resume, the resumed run's): the defaults shown.
    """

    preset: Annotated[Optional[PresetName], tyro.conf.arg(help_behavior_hint="(default: small, or the resumed run's)")] = None
    """paper: the paper's sizes; small: [64, 64] nets (docs/design.md#the-learning-yardstick); tiny: seconds, for tests."""
    eta: Annotated[Optional[tuple[str, ...]], tyro.conf.arg(help_behavior_hint="(default: 0.1)")] = None
    """Grid of shared cooperative ratios, each in [0, 1] or 'auto' (estimated while training: --eta-auto-rule)."""
    eta_per_agent: Optional[tuple[str, ...]] = None
    """Grid of per-agent ratio vectors, each 'A,B,...' with one value (or 'auto') per cooperative agent (rooms − 1)."""
    seeds: Annotated[Optional[int], tyro.conf.arg(help_behavior_hint="(default: 1)")] = None
    """Seeds per ratio: first_seed .. first_seed + seeds − 1."""
    first_seed: int = 0
    """The first seed of --seeds."""
    out: Optional[Path] = None
    """Run folder (default runs/<env>-<algo>-<time>); must not already hold a run."""
    resume: Optional[Path] = None
    """Continue the run in this folder from its latest checkpoint; only --total-steps may change."""
    checkpoint_every: Optional[int] = None
    """Save a checkpoint every K epochs and after the last; 0: only after the last. Default 10 (--resume: the run's)."""
    progress: bool = True
    """Show a progress bar."""
    compile_cache: bool = True
    """Keep compiled programs on disk ($JAX_COMPILATION_CACHE_DIR, else ~/.cache/ccp-jax/xla/<CPU tag>): a run whose grid size and settings were compiled before (other seeds or ratios, a resume) starts without compiling."""
    tensorboard: bool = True
    """Write TensorBoard event files, one folder per grid member (DIR/tb/member_K)."""
    wandb_project: Optional[str] = None
    """Also log to this Weights & Biases project (needs `pip install wandb`)."""
    video_every: Annotated[Optional[int], tyro.conf.arg(help_behavior_hint="(default: 0, or the resumed run's)")] = None
    """Every K epochs, a video of one deterministic evaluation episode of each --video-members member with the stage and η on every frame: DIR/videos/epoch_N_member_K.mp4, also logged to TensorBoard and W&B at the epoch's env steps (docs/videos.md). 0: none."""
    video_members: Annotated[Optional[tuple[int, ...]],
                             tyro.conf.arg(help_behavior_hint="(default: 0, or the resumed run's)")] = None
    """The grid members --video-every films (numbered as in summary.json)."""
    settings: Annotated[Any, tyro.conf.arg(name=""), tyro.conf.OmitArgPrefixes] = dataclasses.field(default_factory=dict)
    """The `Config` settings the command line gives, by flat name (`parse_args`); the others are the preset's (or
    the resumed run's). Their flags are shown with these options and in one group per section (`_REGISTRY`)."""
    devices: tyro.conf.OmitArgPrefixes[Hosts] = Hosts()


# Settings shown with the run options; the others are grouped by their `Config` section (GROUPS). The grid's
# settings are given by --eta / --eta-per-agent / --seeds / --first-seed.
CORE = ("algo", "env", "rooms", "max_episode_steps", "peg_model", "peg_physics", "total_steps", "eta_auto_rule")
GROUPS = ("budget", "sac", "ccp", "tp", "ablations")
PROG = "python -m ccp_jax.train"
DEFAULT_ETA = ("0.1",)  # --eta when neither ratio flag is given (the paper's best 3-room ratio)


def parse_args(argv: Optional[Sequence[str]] = None) -> Args:
    """The command line as `Args`: the run options, and in `settings` the `Config` settings it gives.

    Every setting of `Config` is a flag named after it (`--actor-lr`), typed, documented and defaulted by its
    declaration in ccp_jax/config.py; --help shows the defaults of the --preset (and --resume) given, which are
    read first. A setting counts as given when its flag is on the command line or its value differs from that
    default.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    base = _defaults(argv)
    args = tyro.cli(Args, args=argv, default=Args(settings=_SettingFlags(base)), registry=_REGISTRY, prog=PROG)
    named = _named_flags(argv)
    given = {k: v for k, v in args.settings.items() if k in named or v != base[k]}
    if given.get("primitives") is not None:  # absolute, so a resumed run finds it from any folder
        given["primitives"] = str(Path(given["primitives"]).resolve())
    return dataclasses.replace(args, settings=given)


def _defaults(argv: Sequence[str]) -> dict[str, Any]:
    """The settings a command line starts from: the --resume run's (unreadable: as if new, `resume_config` names
    the fault), with the --preset given on top; else the preset's (default small)."""
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--preset")
    pre.add_argument("--resume", type=Path)
    known, _ = pre.parse_known_args(argv)
    preset = known.preset if known.preset in PRESETS else None
    if known.resume is not None:
        try:
            return {**outputs.read_config(known.resume).flat(), **PRESETS.get(preset, {})}
        except (OSError, ValueError, TypeError, KeyError):  # JSON and config faults are ValueErrors
            pass
    return preset_settings(preset or "small")


def _named_flags(argv: Sequence[str]) -> set[str]:
    """The flat names of the flags on a command line (--actor-lr 1e-3, --actor_lr=1e-3, --no-progress)."""
    names = set()
    for token in argv:
        if token.startswith("--"):
            name = token[2:].partition("=")[0].replace("-", "_")
            names.update((name, name.removeprefix("no_")))
    return names


class _SettingFlags:
    """The default of `Args.settings` while parsing: every setting's value before the command line (`_defaults`).
    `_REGISTRY` shows it to tyro as CORE's flags, then one group per section of GROUPS; tyro gives back a dict."""

    def __init__(self, values: Mapping[str, Any]):
        self.values = values


class _SectionFlags:
    """One section's group of flags (`_SettingFlags`)."""

    def __init__(self, names: Sequence[str], values: Mapping[str, Any]):
        self.names, self.values = names, values


_REGISTRY = tyro.constructors.ConstructorRegistry()


@_REGISTRY.struct_rule
def _settings_rule(info: tyro.constructors.StructTypeInfo) -> Optional[tyro.constructors.StructConstructorSpec]:
    flags = info.default
    if isinstance(flags, _SectionFlags):
        return tyro.constructors.StructConstructorSpec(
            instantiate=dict, fields=tuple(_flag(name, flags.values[name]) for name in flags.names))
    if not isinstance(flags, _SettingFlags):
        return None
    groups = tuple(tyro.constructors.StructFieldSpec(
        name=section, type=tyro.conf.OmitArgPrefixes[_SectionFlags],
        default=_SectionFlags([f.name for f in dataclasses.fields(SECTIONS[section]) if f.name not in CORE],
                              flags.values),
        helptext=" ".join(SECTIONS[section].__doc__.split()))
        for section in GROUPS)

    def instantiate(**given) -> dict:
        return {k: v for name, value in given.items()
                for k, v in (value.items() if name in GROUPS else [(name, value)])}

    return tyro.constructors.StructConstructorSpec(
        instantiate=instantiate, fields=tuple(_flag(name, flags.values[name]) for name in CORE) + groups)


def _flag(name: str, default: Any) -> tyro.constructors.StructFieldSpec:
    """A setting as tyro sees it: its declared type, doc and the given default; a boolean takes a value
    (--maze-slide False), the form the docs and experiment scripts use."""
    section = SECTION_OF[name]
    cls = Config if section is None else SECTIONS[section]
    kind = _types(cls)[name]
    if kind is bool:
        kind = tyro.conf.FlagConversionOff[bool]
    return tyro.constructors.StructFieldSpec(name=name, type=kind, default=default, helptext=_docstrings(cls)[name])


@functools.cache
def _types(cls: type) -> dict[str, Any]:
    """A section's field types, resolved (config.py's annotations are strings)."""
    return typing.get_type_hints(cls, localns={"EtaAutoRule": EtaAutoRule})


@functools.cache
def _docstrings(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass, by field name, as one line."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    return {node.target.id: " ".join(doc.value.value.split()) for node, doc in zip(body, body[1:])
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
            and isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant) and isinstance(doc.value.value, str)}


def config_from_args(args: Args, base: Optional[Config] = None) -> Config:
    """The validated `Config` the arguments describe, on top of `base` (a resumed run) or the preset."""
    if args.seeds is not None and args.seeds < 1:
        raise ConfigError("seeds", f"must be >= 1, got {args.seeds}")
    if args.eta is not None and args.eta_per_agent is not None:
        raise ConfigError("eta", "give either --eta or --eta-per-agent, not both")
    fields = {} if base is None else base.flat()
    if base is None or args.preset is not None:
        fields.update(PRESETS[args.preset or "small"])
    explicit = dict(args.settings)
    if args.eta_per_agent is not None:
        explicit["etas"] = tuple(parse_eta_vector(t) for t in args.eta_per_agent)
    elif args.eta is not None or base is None:
        explicit["etas"] = tuple((parse_eta(x),) for x in (args.eta or DEFAULT_ETA))
    if args.seeds is not None or base is None:
        explicit["seeds"] = tuple(range(args.first_seed, args.first_seed + (args.seeds or 1)))
    fields.update(explicit)
    if "rooms" in args.settings and fields.get("env", "maze") != "maze":  # else silently replaced by the env's stages
        raise ConfigError("rooms", f"--rooms sets the maze's number of rooms; env {fields['env']!r} has its own stages")
    if ":" in fields.get("env", ""):  # a user's env decides its own number of stages, once it is checked
        fields["rooms"] = user_env(fields["env"], check=True).num_stages
    config = make_config("paper", **fields)
    if config.algo != "csac" and (args.eta is not None or args.eta_per_agent is not None):
        raise ConfigError("eta", f"--algo {config.algo} trains every agent on its own critic alone (η = 1): a ratio "
                                 "changes nothing; leave --eta and --eta-per-agent out")
    if args.eta_per_agent is not None:
        check_per_agent_lengths(config)
    if config.algo == "tp":  # the primitives' run must exist and match, before anything compiles
        primitives_config(config)
    return config


def check_per_agent_lengths(config: Config) -> None:
    """`--eta-per-agent` vectors give every cooperative agent a value. `Config` reads a 1-value vector as a
    shared ratio; from this flag, with more than one cooperative agent, it is a slip (e.g. a space for a comma)."""
    n = config.num_agents
    for eta in config.grid.etas:
        if len(eta) == 1 and n > 2:
            example = ",".join([outputs.eta_text([eta[0]])] * (n - 1))
            raise ConfigError("eta_per_agent", f"ratio vector {outputs.eta_text(eta)} has 1 value; {n} agents need "
                              f"{n - 1} values, comma-separated (e.g. {example}); for one ratio shared by every "
                              "agent use --eta")


RUN_OPTIONS = "run.json"  # the run's options that are not settings of what it trains, which --resume keeps
# Each run option's value when neither the command line nor run.json gives it (run.json from before it existed).
RUN_DEFAULTS = {"checkpoint_every": 10, "video_every": 0, "video_members": (0,)}


def run_options(args: Args, run_dir: Optional[Path] = None) -> dict[str, Any]:
    """The run options (`RUN_DEFAULTS`' names): those the arguments give, else the resumed run's in `run_dir`'s
    run.json, else the defaults."""
    saved = dict(RUN_DEFAULTS)
    path = None if run_dir is None else Path(run_dir) / RUN_OPTIONS
    if path is not None and path.exists() and any(getattr(args, name) is None for name in RUN_DEFAULTS):
        try:
            found = json.loads(path.read_text())
            saved.update({"checkpoint_every": int(found["checkpoint_every"]),
                          "video_every": int(found.get("video_every", saved["video_every"])),
                          "video_members": tuple(int(k) for k in found.get("video_members", saved["video_members"]))})
        except (ValueError, KeyError, TypeError) as err:
            raise ConfigError("resume", f"{path} is unreadable ({err}); repair it or give --checkpoint-every, "
                                        "--video-every and --video-members") from None
    return {name: saved[name] if getattr(args, name) is None else getattr(args, name) for name in RUN_DEFAULTS}


def prepare_out(out: Optional[Path], config: Config) -> Path:
    """Creates the run folder; refuses one that already holds a run, so nothing is overwritten."""
    if out is None:
        out = Path("runs") / f"{config.task.env.replace(':', '_')}-{config.algo}-{time.strftime('%Y%m%d-%H%M%S')}"
    if out.exists() and not out.is_dir():
        raise ConfigError("out", f"{out} is a file, not a folder; choose another --out")
    checkpoints = out / checkpoint.CHECKPOINT_DIR
    held = [name for name in ("config.json", "metrics.jsonl", "metrics.jsonl.gz", "summary.json") if (out / name).exists()]
    if checkpoints.is_dir() and any(checkpoints.iterdir()):  # another run's: they would be mixed with this one's
        held.append(checkpoint.CHECKPOINT_DIR)
    if held:
        raise ConfigError("out", f"{out} already holds a run ({', '.join(held)}); choose another --out, or continue it "
                                 f"with --resume {out}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:  # under a file, no permission, a read-only or virtual file system
        raise ConfigError("out", f"cannot create {out} ({err.strerror or err}); choose another --out") from None
    return out


def planned_grid_size(args: Args) -> Optional[int]:
    """The number of runs the arguments ask for, read without starting JAX (the CPU split must come first);
    None where it cannot be read yet (an unreadable --resume folder: `resume_config` names the fault)."""
    if args.resume is not None:
        try:
            return outputs.read_config(args.resume).grid_size
        except (OSError, ValueError, TypeError, KeyError):  # JSON and config faults are ValueErrors
            return None
    ratios = len(args.eta_per_agent if args.eta_per_agent is not None else args.eta or DEFAULT_ETA)
    return max(1, ratios * (args.seeds or 1))


def resume_config(args: Args) -> Config:
    """The resumed run's config; arguments given again must agree with it (total_steps may grow)."""
    run_dir = args.resume
    saved = outputs.read_config(run_dir, field="resume")
    saved.check_trainable()  # first: the comparison below would name a retired setting's default, not the setting
    if args.out is not None and args.out != run_dir:
        raise ConfigError("out", f"--out {args.out} differs from --resume {run_dir}; give only --resume")

    trained = saved.flat()

    def refused(name: str, got) -> ConfigError:
        return ConfigError(name, f"the run in {run_dir} was trained with {trained[name]!r}, got {got!r}; "
                                 "start a new run to change it")

    # Settings given again are compared before the config is built: a changed one (algo, rooms, env) can make the
    # saved ratios invalid, and that error would not name what changed.
    for name, got in args.settings.items():
        if name != "total_steps" and got != trained[name]:
            raise refused(name, got)
    config = config_from_args(args, base=saved)
    if changed := saved.differing(config, ignore=("total_steps",)):
        raise refused(changed[0], config.flat()[changed[0]])
    return config


def resume_point(mngr: checkpoint.ocp.CheckpointManager, rows: list[dict], grid_size: int) -> Optional[int]:
    """The checkpoint a resume starts from: the latest one that the rows of metrics.jsonl reach.

    Rows are written before each checkpoint, so a checkpoint past the complete rows (a row cut by a crash) is
    trained again from an earlier one, deterministically, into the same checkpoints. Rows that end before the
    oldest checkpoint (a truncated or replaced file) would leave a hole in the metrics: refused. None when no
    checkpoint exists (`checkpoint.restore` says what to do).
    """
    steps = mngr.all_steps()
    complete = outputs.complete_epochs(rows, grid_size)
    if not steps:
        return None
    if not (covered := [s for s in steps if s <= complete]):
        have = f"epochs 1-{complete}" if complete else "no complete epoch"
        raise ConfigError("resume", f"metrics.jsonl in {Path(mngr.directory).parent} holds {have}, but its oldest "
                                    f"checkpoint is of epoch {min(steps)}: resuming would leave epochs "
                                    f"{complete + 1}-{min(steps)} without metrics. Restore the metrics file, or "
                                    "start the run again with another --out")
    return max(covered)


def _restore(mngr: checkpoint.ocp.CheckpointManager, trainer: Any, seed: np.ndarray, grid_size: int,
             epoch: Optional[int], lead: bool) -> tuple[int, Any]:
    """Checkpoint `epoch` (None: the latest) restored for `trainer`; a damaged one gives way to the next older,
    which the rows cover too, with a warning (the epochs after it are trained again, deterministically)."""
    def restore(candidate: Optional[int]) -> tuple[int, Any]:
        return checkpoint.restore(mngr, trainer.abstract_state(seed), grid_size=grid_size, epoch=candidate,
                                  defaults=lambda: trainer.init(seed))  # for fields added since

    candidates = [epoch, *sorted((s for s in mngr.all_steps() if epoch is not None and s < epoch), reverse=True)]
    for candidate, older in zip(candidates, candidates[1:]):
        try:
            return restore(candidate)
        except checkpoint.UnreadableCheckpoint as err:
            if lead:
                print(f"warning: {str(err).split('; earlier')[0]}; resuming from checkpoint {older} instead (the "
                      "damaged one is replaced)")
    return restore(candidates[-1])


def run(config: Config, out: Path, progress: bool = True, resume: bool = False,
        checkpoint_every: int = 10, tensorboard: bool = True, wandb_project: Optional[str] = None,
        members_at_once: Optional[int] = None, devices: Optional[list] = None, video_every: int = 0,
        video_members: Sequence[int] = (0,)) -> dict:
    """Trains the grid of `config` in `out`: config.json, metrics.jsonl, summary.json, checkpoints/ (videos/).

    With `resume`, continues from the latest checkpoint in `out`; metrics rows (and videos)
    written after that checkpoint are replaced by their recomputation (identical on the same device split).
    `members_at_once`: see `GridTrainer` (default: `devices.default_members_at_once`).
    `devices`: what the grid trains on (default: `grid_devices`); a resumed run may use another split
    than its checkpoint's (`checkpoint.restore` pads the grid anew).
    `video_every`, `video_members`: `ccp_jax.video`; an env that cannot be drawn is refused before training.
    Returns the summary (per member: final success = mean of the last 10 epochs).
    """
    config.check_trainable()
    video.check_options(config, video_every, video_members)
    # A refused resume (damaged rows, a hole before the checkpoints) or an env that cannot be drawn stops here,
    # before anything is written, compiled or logged.
    rows = outputs.read_rows(out / outputs.METRICS, field="resume") if resume else []
    env = make_env(config)
    videos = (video.Videos(config, env, make_networks(config, env.action_size).actor, out, video_every, video_members)
              if video_every else None)
    mngr = checkpoint.manager(out)
    resume_epoch = resume_point(mngr, rows, config.grid_size) if resume else None
    sinks = loggers.make_loggers(out, config, tensorboard, wandb_project)
    options = {"checkpoint_every": checkpoint_every, "video_every": video_every, "video_members": list(video_members)}
    try:
        return _train(config, env, out, progress, mngr, (rows, resume_epoch) if resume else None, options, sinks,
                      members_at_once, devices or grid_devices(config.grid_size), videos)
    finally:
        sinks.close()


def _train(config: Config, env, out: Path, progress: bool, mngr: checkpoint.ocp.CheckpointManager,
           resumed: Optional[tuple[list[dict], Optional[int]]], options: dict, sinks: loggers.Loggers,
           members_at_once: Optional[int], devices: list, videos: Optional[video.Videos]) -> dict:
    """`run`'s training loop once the folder is checked; `resumed`: the rows so far and the checkpoint to start
    from (`resume_point`); `options`: the run options run.json keeps (`RUN_DEFAULTS`' names)."""
    metrics_path = out / outputs.METRICS
    rows, resume_epoch = resumed or ([], None)
    make = make_tp_grid if config.algo == "tp" else make_grid_train
    trainer = make(config, env, devices, members_at_once=members_at_once)
    eta, seed = config.grid_arrays()
    lead = jax.process_index() == 0  # with several hosts, one writes the files; all save checkpoints
    start = time.time()
    if resumed is not None:
        first_epoch, state = _restore(mngr, trainer, seed, config.grid_size, resume_epoch, lead)
        if first_epoch > config.num_epochs:
            raise ConfigError("total_steps", f"the run already has {first_epoch} epochs, more than {config.num_epochs}")
        for later in [s for s in mngr.all_steps() if s > first_epoch]:  # only once the covered one restored
            mngr.delete(later)
        rows = [r for r in rows if r["epoch"] <= first_epoch]
        if lead:
            outputs.write_rows(metrics_path, rows)
            (out / outputs.COMPACTED).unlink(missing_ok=True)  # a compacted run's rows are raw again, to append to
            video.forget_after(out, first_epoch)
            sinks.resume(rows[-1]["env_steps"])  # the restored checkpoint's: a damaged newer one may have given way
    else:
        first_epoch, state = 0, trainer.init(seed)
    start -= sum(r["epoch_wall_s"] for r in rows if r["member"] == 0)  # a resumed run's earlier epochs count too
    if lead:
        outputs.write_json(out / "config.json", config.to_dict())
        outputs.write_json(out / RUN_OPTIONS, options)  # what --resume keeps

    every = options["checkpoint_every"]
    bar = tqdm(range(first_epoch, config.num_epochs), initial=first_epoch, total=config.num_epochs,
               desc=f"{config.algo} {config.task.env} x{config.grid_size}", unit="epoch",
               disable=not (progress and lead), dynamic_ncols=True)
    # The first epoch includes compiling it: say so, as MJX envs on a CPU compile for minutes.
    bar.set_postfix_str("compiling the epoch program (once)")
    # Members whose earlier epochs already diverged were reported then (the summary says it again).
    diverged = {r["member"] for r in rows if outputs.divergence(r, config.value_bound)}
    for epoch in bar:
        t0 = time.time()
        state, metrics = trainer.train_step(state, eta)
        metrics = to_host(metrics)
        epoch_rows = outputs.metric_rows(config, epoch + 1, metrics, time.time() - t0)
        if lead:
            outputs.append_rows(metrics_path, epoch_rows)
            sinks.write(epoch_rows)
        rows.extend(epoch_rows)
        for row in epoch_rows:  # said as it happens: a grid can train on for hours after one member diverges
            if row["member"] not in diverged and (why := outputs.divergence(row, config.value_bound)):
                diverged.add(row["member"])
                if lead:
                    bar.write(outputs.diverged_warning(row["member"], row["seed"], row["env_steps"], why))
        if videos is not None and videos.due(epoch + 1):  # before the checkpoint: a crash here films it again
            actors = to_host(state.agents.actor)  # on every host: a multi-host gather is collective
            if lead:
                videos.record(epoch + 1, actors, epoch_rows, sinks)
        if epoch + 1 == config.num_epochs or (every and (epoch + 1) % every == 0):
            checkpoint.save(mngr, epoch + 1, state)
        success = np.asarray(metrics.eval.success_rate)
        bar.set_postfix(steps=f"{int(metrics.env_steps.max()):,}", best_success=f"{success.max():.2f}",
                        mean_success=f"{success.mean():.2f}")
    mngr.close()
    summary = outputs.summarise(config, rows, wall_s=time.time() - start)
    summary["devices"] = f"{len(trainer.devices)} {trainer.devices[0].platform}"  # wall_s is for this split
    if lead:
        outputs.write_json(out / "summary.json", summary)
    return summary


def enable_compile_cache() -> Path:
    """Turns on JAX's persistent compilation cache and returns its folder.

    A folder the user chose (JAX_COMPILATION_CACHE_DIR or jax.config) is kept;
    otherwise $XDG_CACHE_HOME/ccp-jax/xla/<host CPU tag> (default ~/.cache; one
    folder per CPU model and feature set, `devices.host_cpu_tag`). Seeds and ratios
    are inputs of the compiled epoch, not constants, so a sweep of other seeds
    or ratios at the same grid size reuses the program. Call before compiling.
    """
    if not jax.config.jax_compilation_cache_dir:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
        jax.config.update("jax_compilation_cache_dir", str(base / "ccp-jax" / "xla" / host_cpu_tag()))
    return Path(jax.config.jax_compilation_cache_dir)


def to_host(tree):
    """Numpy copies of (possibly multi-host, sharded) arrays."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    return multihost_utils.process_allgather(tree, tiled=True)


def main(argv: Optional[list[str]] = None) -> dict:
    args = parse_args(argv)
    hosts = args.devices
    if hosts.cpu_devices != "auto" and hosts.cpu_devices < 1:
        raise ConfigError("cpu_devices", f"must be >= 1 or auto, got {hosts.cpu_devices}")
    envs_mjx.configure_cpu()  # before anything starts JAX (the `ccp-train` entry point comes here)
    split_host_cpu(hosts.cpu_devices, planned_grid_size(args))
    if hosts.distributed:
        jax.distributed.initialize(coordinator_address=hosts.coordinator, num_processes=hosts.num_processes,
                                   process_id=hosts.process_id)
    if args.checkpoint_every is not None and args.checkpoint_every < 0:
        raise ConfigError("checkpoint_every", f"must be >= 0, got {args.checkpoint_every}")
    check_members_at_once(hosts.members_at_once)  # before the run folder is made
    if args.compile_cache:
        enable_compile_cache()
    if args.resume is not None:
        config, out = resume_config(args), args.resume
        options = run_options(args, out)
    else:
        config = config_from_args(args)
        options = run_options(args)
        video.check_options(config, options["video_every"], options["video_members"])  # before the folder exists
        out = prepare_out(args.out, config)
    if jax.process_count() > 1:  # every host checks the folder before any host writes to it
        multihost_utils.sync_global_devices("run folder checked")
    devices = grid_devices(config.grid_size)
    print(f"{'Resuming' if args.resume else 'Training'} {config.grid_size} run(s) of {config.algo} on "
          f"{config.task.env} ({config.num_stages} stages, {config.num_epochs} epochs of {config.budget.steps_per_epoch} steps) on "
          f"{len(devices)} {devices[0].platform} device{'s' * (len(devices) > 1)} -> {out}")
    summary = run(config, out, progress=args.progress, resume=args.resume is not None, tensorboard=args.tensorboard,
                  wandb_project=args.wandb_project, members_at_once=hosts.members_at_once, devices=devices, **options)
    print(outputs.summary_table(summary))
    print(f"wall time {summary['wall_s']:.0f} s; files in {out}")
    return summary


def cli() -> None:
    """Console entry: bad input ends with one line naming the field, no traceback."""
    try:
        main()
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from None
    except OSError as err:
        if err.errno != errno.ENOSPC:
            raise
        raise SystemExit(f"error: out: no space left on the device ({err.filename or 'writing the run'}); the "
                         "folder keeps its last checkpoint: free space (or move the folder), then continue it with "
                         "--resume") from None


if __name__ == "__main__":
    cli()
