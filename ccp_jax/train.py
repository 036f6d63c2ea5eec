"""Command line and Python entry point: train a whole grid of runs in one program.

    python -m ccp_jax.train --env maze --rooms 3 --algo csac --eta 0.1 0.5 0.9 --seeds 5 --out runs/x

The host loop below only logs, shows progress and saves; each epoch of every
grid member is one call of the compiled, vmapped `train_step`.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":  # the CLI: MJX's CPU flag and quiet import, before the imports below load brax and MJX
    envs_mjx.configure_cpu()

import dataclasses
import os
import time
from pathlib import Path
from typing import Literal, Optional

import jax
import numpy as np
import tyro
from jax.experimental import multihost_utils
from tqdm.auto import tqdm

from ccp_jax import checkpoint, loggers, outputs
from ccp_jax.devices import CpuDevices, grid_devices, split_host_cpu
from ccp_jax.config import (PRESETS, Config, ConfigError, CoopScale, NetworkInit, NextAction, Normaliser, PresetName, TanhLogProb,
                             make_config)
from ccp_jax.eta import EtaAutoRule, parse_eta, parse_eta_vector
from ccp_jax.envs import make_env, user_env
from ccp_jax.grid import check_members_at_once, make_grid_train
from ccp_jax.tp.primitives import primitives_config
from ccp_jax.tp.trainer import make_tp_grid


@dataclasses.dataclass
class Args:
    """Train CSAC (or a baseline) on a multi-stage task; every ratio × seed in one vmapped program.

    Options left unset take the preset's value (or, with --resume, the resumed run's).
    """

    env: Optional[str] = None
    """Environment: maze (default), peg, pusher, or 'module.path:factory' returning an env that meets the contract (check it with envs_mjx.contract.check_env)."""
    rooms: Optional[int] = None
    """Number of maze rooms (stages); default 2."""
    algo: Optional[Literal["csac", "naive", "sac", "tp"]] = None
    """csac (default): cooperative agents; naive: independent agents; sac: one end-to-end agent; tp: transition policies between frozen primitives (needs --primitives)."""
    primitives: Optional[Path] = None
    """--algo tp: run folder of a finished --algo naive run (same env and rooms) whose agents are the frozen primitives."""
    primitives_member: Optional[int] = None
    """--algo tp: which grid member of the --primitives run supplies the primitives (default 0)."""
    tp_max_steps: Optional[int] = None
    """--algo tp: transition steps before termination is forced (default 100)."""
    tp_init_episodes: Optional[int] = None
    """--algo tp: deterministic primitive episodes that seed the permanent success states (default 100)."""
    tp_prox_updates: Optional[int] = None
    """--algo tp: proximity-predictor Adam steps per epoch (default 785)."""
    tp_ppo_epochs: Optional[int] = None
    tp_buffer_size: Optional[int] = None
    eta: Optional[tuple[str, ...]] = None
    """Grid of shared cooperative ratios, each in [0, 1] or 'auto' (running η*); default 0.1."""
    eta_per_agent: Optional[tuple[str, ...]] = None
    """Grid of per-agent ratio vectors, each 'A,B,...' with one value (or 'auto') per cooperative agent (rooms − 1)."""
    seeds: Optional[int] = None
    """Seeds per ratio (default 1): first_seed .. first_seed + seeds − 1."""
    first_seed: int = 0
    preset: Optional[PresetName] = None
    """paper: the paper's sizes; small (default): [64, 64] nets (SPEC §7); tiny: seconds-scale, for tests."""
    total_steps: Optional[int] = None
    """Environment steps per run (default: the preset's). May be raised when resuming."""
    out: Optional[Path] = None
    """Run folder (default runs/<env>-<algo>-<time>); must not already hold a run."""
    resume: Optional[Path] = None
    """Continue the run in this folder from its latest checkpoint."""
    checkpoint_every: int = 10
    """Save a checkpoint every K epochs (and always after the last); 0: only after the last."""
    maze_reverse: Optional[bool] = None
    """Maze: True lets a[0] < 0 drive the robot backwards (v = a[0] v_max); default False: v = (a[0] + 1)/2 v_max."""
    maze_slide: Optional[bool] = None
    """Maze: a step blocked by a wall slides along it (default True; False: it stops there)."""
    num_envs: Optional[int] = None
    hidden: Optional[tuple[int, ...]] = None
    network_init: Optional[NetworkInit] = None
    """Initial weights: flax (default: lecun-normal kernels) or rlkit (RLkit's SAC: fan-in uniform hidden layers, last layers U(±3e-3) critic / U(±1e-3) actor)."""
    batch_size: Optional[int] = None
    buffer_size: Optional[int] = None
    steps_per_epoch: Optional[int] = None
    train_loops_per_epoch: Optional[int] = None
    train_cycles_per_epoch: Optional[int] = None
    """Split each epoch into K cycles of (collect, update) (default 1, the paper's: all steps, then all updates)."""
    eval_episodes: Optional[int] = None
    max_episode_steps: Optional[int] = None
    gamma: Optional[float] = None
    tau: Optional[float] = None
    """Polyak rate of the target critics (default 0.005)."""
    actor_lr: Optional[float] = None
    critic_lr: Optional[float] = None
    alpha_lr: Optional[float] = None
    target_entropy: Optional[float] = None
    """Entropy the temperatures α steer the policies towards (default −|A|, the action size negated)."""
    initial_alpha: Optional[float] = None
    """Every temperature α before training (default 1, RLkit's)."""
    start_steps: Optional[int] = None
    """Uniform-random env steps before the policies act (default 1000)."""
    normalise_last: Optional[bool] = None
    """The last agent's actor uses its normalised critic (η_N = 1 on Q̂_N) instead of the plain SAC loss."""
    eta_auto_range: Optional[tuple[float, float]] = None
    """--eta auto: the interval η* is clipped to (default 0.05 0.95)."""
    eta_auto_next_weight: Optional[float] = None
    """--eta auto: κ in η* = Ran(Q_n) / (Ran(Q_n) + κ Ran(Q_{n+1})), the ratio whose objective is Q_n + κ Q_{n+1} (default 1, the paper's appendix)."""
    eta_auto_rule: Optional[EtaAutoRule] = None
    """--eta auto follows: ranges (η* of the critics' running ranges, the paper's appendix, default), outcomes (each epoch η_n moves by --eta-auto-rate × (training episodes failing in stage n − those failing in stage n + 1) / those entering stage n, from the middle of --eta-auto-range), gated (outcomes with only the upward term until a training episode has succeeded in stage n + 1, only the downward term after) or trusted (as gated, but before that success both terms, with η no lower than the middle of --eta-auto-range)."""
    eta_auto_rate: Optional[float] = None
    """--eta auto with --eta-auto-rule outcomes, gated or trusted: η's largest move per epoch (default 0.05)."""
    eta_auto_up_rate: Optional[float] = None
    """--eta-auto-rule outcomes, gated or trusted: the rate of the own-failure (upward) term if it differs from --eta-auto-rate; 0: η only falls."""
    eta_auto_floor_step: Optional[float] = None
    """--eta-auto-rule outcomes, gated or trusted: agent n's ratio falls no lower than the low end of --eta-auto-range + n × this (at most the range's middle); default 0."""
    normaliser: Optional[Normaliser] = None
    """How critics are scaled in the actor loss: batch (the paper's, default), ema (running min/max), floor, none (raw Q: C_n is the value of the cooperative reward η r_n + (1 − η) r_{n+1})."""
    norm_floor: Optional[float] = None
    """Smallest range the floor normaliser divides by, in reward units (default 1)."""
    norm_ema_rate: Optional[float] = None
    coop_scale: Optional[CoopScale] = None
    """Units of the cooperative objective in the actor loss: unit (the paper's, normalised to [0, 1], default) or own (times the own critic's normaliser scale: α in Q_n's units, as Naive's; η = 1 is Naive)."""
    absorbing_stages: Optional[bool] = None
    """Critic n bootstraps the exact value 1/(1 − γ) once stage n is done (default on; off = the paper's literal rule)."""
    next_action: Optional[NextAction] = None
    """Whose action bootstraps critic targets at s': own (the paper's π_n, default) or acting (π_{n+1} once s' is in stage n+1)."""
    absorbing_success: Optional[bool] = None
    """Success bootstraps the absorbing value of all-ones rewards (default on; off = success ends with value 0)."""
    tanh_log_prob: Optional[TanhLogProb] = None
    """The tanh correction in log π: exact (default) or rlkit (RLkit's log(1 − tanh² + 1e-6), capped at saturation)."""
    cpu_devices: CpuDevices = "auto"
    """On a CPU: split it into this many XLA devices, so grid members train side by side (auto: the count that wastes least for this grid, of up to twice the cores, ccp_jax.devices.grid_devices: one run keeps the whole CPU as one device, 3 runs on 2 cores take 3; 1: the whole CPU as one device). A count set in $XLA_FLAGS wins. Does not change results beyond float rounding."""
    members_at_once: Optional[int] = None
    """Grid members each device advances together (vmapped); the rest run one group after another in the same program. Default: all on GPU/TPU; on a CPU device of several cores as many as keep the stacked critic activations small (ccp_jax.devices.default_members_at_once: 12 [64, 64] SAC members, 4 2-agent or 2 3-agent CSAC members), on a CPU split into a device per core 1. Does not change results beyond float rounding."""
    progress: bool = True
    """Show a progress bar."""
    compile_cache: bool = True
    """Keep compiled programs on disk ($JAX_COMPILATION_CACHE_DIR, else ~/.cache/ccp-jax/xla): a run whose grid size and settings were compiled before (other seeds or ratios, a resume) starts without compiling."""
    tensorboard: bool = True
    """Write TensorBoard event files, one folder per grid member (DIR/tb/member_K)."""
    wandb_project: Optional[str] = None
    """Also log to this Weights & Biases project (needs `pip install wandb`)."""
    distributed: bool = False
    """Multi-host: call jax.distributed.initialize() first (every host runs the same command; see README)."""
    coordinator: Optional[str] = None
    """With --distributed: host0:port of the coordinator (auto-detected on SLURM, Open MPI, Kubernetes, Cloud TPU)."""
    num_processes: Optional[int] = None
    process_id: Optional[int] = None


OVERRIDES = ("maze_reverse", "maze_slide", "total_steps", "num_envs", "hidden", "network_init", "batch_size",
             "buffer_size", "steps_per_epoch", "train_loops_per_epoch", "train_cycles_per_epoch", "eval_episodes", "max_episode_steps", "gamma", "absorbing_stages",
             "absorbing_success", "tanh_log_prob", "normaliser", "norm_floor", "norm_ema_rate", "coop_scale", "next_action", "tau",
             "actor_lr", "critic_lr", "alpha_lr", "target_entropy", "initial_alpha", "start_steps", "normalise_last", "eta_auto_range",
             "eta_auto_next_weight", "eta_auto_rule", "eta_auto_rate", "eta_auto_up_rate", "eta_auto_floor_step",
             "primitives_member", "tp_max_steps", "tp_init_episodes", "tp_prox_updates", "tp_ppo_epochs", "tp_buffer_size")


DEFAULT_ETA = ("0.1",)  # --eta when neither ratio flag is given (the paper's best 3-room ratio)


def config_from_args(args: Args, base: Optional[Config] = None) -> Config:
    """The validated `Config` the arguments describe, on top of `base` (a resumed run) or the preset."""
    if args.seeds is not None and args.seeds < 1:
        raise ConfigError("seeds", f"must be >= 1, got {args.seeds}")
    if args.eta is not None and args.eta_per_agent is not None:
        raise ConfigError("eta", "give either --eta or --eta-per-agent, not both")
    fields = {} if base is None else dataclasses.asdict(base)
    if base is None or args.preset is not None:
        preset = args.preset or "small"
        if preset not in PRESETS:
            raise ConfigError("preset", f"unknown preset {preset!r}; choose one of {tuple(PRESETS)}")
        fields.update(PRESETS[preset])
    explicit = {k: getattr(args, k) for k in ("env", "rooms", "algo") + OVERRIDES if getattr(args, k) is not None}
    if args.eta_per_agent is not None:
        explicit["etas"] = tuple(parse_eta_vector(t) for t in args.eta_per_agent)
    elif args.eta is not None or base is None:
        explicit["etas"] = tuple((parse_eta(x),) for x in (args.eta or DEFAULT_ETA))
    if args.seeds is not None or base is None:
        explicit["seeds"] = tuple(range(args.first_seed, args.first_seed + (args.seeds or 1)))
    if args.primitives is not None:  # absolute, so a resumed run finds it from any folder
        explicit["primitives"] = str(args.primitives.resolve())
    fields.update(explicit)
    if args.rooms is not None and fields.get("env", "maze") != "maze":  # else silently replaced by the env's stages
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
    for eta in config.etas:
        if len(eta) == 1 and n > 2:
            example = ",".join([outputs.eta_text([eta[0]])] * (n - 1))
            raise ConfigError("eta_per_agent", f"ratio vector {outputs.eta_text(eta)} has 1 value; {n} agents need "
                              f"{n - 1} values, comma-separated (e.g. {example}); for one ratio shared by every "
                              "agent use --eta")


def prepare_out(out: Optional[Path], config: Config) -> Path:
    """Creates the run folder; refuses one that already holds a run, so nothing is overwritten."""
    if out is None:
        out = Path("runs") / f"{config.env.replace(':', '_')}-{config.algo}-{time.strftime('%Y%m%d-%H%M%S')}"
    if (out / "config.json").exists() or (out / "metrics.jsonl").exists():
        raise ConfigError("out", f"{out} already holds a run; choose another --out, or continue it with --resume {out}")
    out.mkdir(parents=True, exist_ok=True)
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
    if args.out is not None and args.out != run_dir:
        raise ConfigError("out", f"--out {args.out} differs from --resume {run_dir}; give only --resume")

    def refused(name: str, got) -> ConfigError:
        return ConfigError(name, f"the run in {run_dir} was trained with {getattr(saved, name)!r}, got {got!r}; "
                                 "start a new run to change it")

    # Fields given again are compared before the config is built: a changed one (algo, rooms, env) can make the
    # saved ratios invalid, and that error would not name what changed.
    for name in ("env", "rooms", "algo") + OVERRIDES:
        got = getattr(args, name)
        if name != "total_steps" and got is not None and got != getattr(saved, name):
            raise refused(name, got)
    config = config_from_args(args, base=saved)
    if changed := saved.differing(config, ignore=("total_steps",)):
        raise refused(changed[0], getattr(config, changed[0]))
    return config


def run(config: Config, out: Path, progress: bool = True, resume: bool = False,
        checkpoint_every: int = 10, tensorboard: bool = True, wandb_project: Optional[str] = None,
        members_at_once: Optional[int] = None, devices: Optional[list] = None) -> dict:
    """Trains the grid of `config` in `out`: config.json, metrics.jsonl, summary.json, checkpoints/.

    With `resume`, continues from the latest checkpoint in `out`; metrics rows
    written after that checkpoint are replaced by their recomputation (identical on the same device split).
    `members_at_once`: see `GridTrainer` (default: `devices.default_members_at_once`).
    `devices`: what the grid trains on (default: `grid_devices`); a resumed run may use another split
    than its checkpoint's (`checkpoint.restore` pads the grid anew).
    Returns the summary (per member: final success = mean of the last 10 epochs).
    """
    sinks = loggers.make_loggers(out, config, tensorboard, wandb_project)  # fails before compiling
    try:
        return _train(config, out, progress, resume, checkpoint_every, sinks, members_at_once,
                      devices or grid_devices(config.grid_size))
    finally:
        sinks.close()


def _train(config: Config, out: Path, progress: bool, resume: bool, checkpoint_every: int,
           sinks: loggers.Loggers, members_at_once: Optional[int], devices: list) -> dict:
    metrics_path = out / "metrics.jsonl"
    rows = outputs.read_rows(metrics_path, field="resume") if resume else []  # a damaged file stops us before tracing
    env = make_env(config)
    make = make_tp_grid if config.algo == "tp" else make_grid_train
    trainer = make(config, env, devices, members_at_once=members_at_once)
    eta, seed = config.grid_arrays()
    lead = jax.process_index() == 0  # with several hosts, one writes the files; all save checkpoints
    mngr = checkpoint.manager(out)
    start = time.time()
    if resume:
        # Rows are written before each checkpoint; a checkpoint past the rows that survived (a row cut by a
        # crash) would leave a hole in metrics.jsonl, so resume from the latest one they cover and train the
        # later epochs again (deterministically, into the same checkpoints).
        covered = [s for s in mngr.all_steps() if s <= outputs.complete_epochs(rows, config.grid_size)]
        first_epoch, state = checkpoint.restore(mngr, trainer.abstract_state(seed), grid_size=config.grid_size,
                                                epoch=max(covered) if covered else None,
                                                defaults=lambda: trainer.init(seed))  # for fields added since
        if first_epoch > config.num_epochs:
            raise ConfigError("total_steps", f"the run already has {first_epoch} epochs, more than {config.num_epochs}")
        for later in [s for s in mngr.all_steps() if s > first_epoch]:  # only once the covered one restored
            mngr.delete(later)
        rows = [r for r in rows if r["epoch"] <= first_epoch]
        if lead:
            outputs.write_rows(metrics_path, rows)
            (out / outputs.COMPACTED).unlink(missing_ok=True)  # a compacted run's rows are raw again, to append to
    else:
        first_epoch, state = 0, trainer.init(seed)
    start -= sum(r["epoch_wall_s"] for r in rows if r["member"] == 0)  # a resumed run's earlier epochs count too
    if lead:
        outputs.write_json(out / "config.json", config.to_dict())

    bar = tqdm(range(first_epoch, config.num_epochs), initial=first_epoch, total=config.num_epochs,
               desc=f"{config.algo} {config.env} x{config.grid_size}", unit="epoch",
               disable=not (progress and lead), dynamic_ncols=True)
    # The first epoch includes compiling it: say so, as MJX envs on a CPU compile for minutes.
    bar.set_postfix_str("compiling the epoch program (once)")
    for epoch in bar:
        t0 = time.time()
        state, metrics = trainer.train_step(state, eta)
        metrics = to_host(metrics)
        epoch_rows = outputs.metric_rows(config, epoch + 1, metrics, time.time() - t0)
        if lead:
            outputs.append_rows(metrics_path, epoch_rows)
            sinks.write(epoch_rows)
        rows.extend(epoch_rows)
        if epoch + 1 == config.num_epochs or (checkpoint_every and (epoch + 1) % checkpoint_every == 0):
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
    otherwise $XDG_CACHE_HOME/ccp-jax/xla (default ~/.cache). Seeds and ratios
    are inputs of the compiled epoch, not constants, so a sweep of other seeds
    or ratios at the same grid size reuses the program. Call before compiling.
    """
    if not jax.config.jax_compilation_cache_dir:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
        jax.config.update("jax_compilation_cache_dir", str(base / "ccp-jax" / "xla"))
    return Path(jax.config.jax_compilation_cache_dir)


def to_host(tree):
    """Numpy copies of (possibly multi-host, sharded) arrays."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    return multihost_utils.process_allgather(tree, tiled=True)


def main(argv: Optional[list[str]] = None) -> dict:
    args = tyro.cli(Args, args=argv)
    if args.cpu_devices != "auto" and args.cpu_devices < 1:
        raise ConfigError("cpu_devices", f"must be >= 1 or auto, got {args.cpu_devices}")
    envs_mjx.configure_cpu()  # before anything starts JAX (the `ccp-train` entry point comes here)
    split_host_cpu(args.cpu_devices, planned_grid_size(args))
    if args.distributed:
        jax.distributed.initialize(coordinator_address=args.coordinator, num_processes=args.num_processes,
                                   process_id=args.process_id)
    if args.checkpoint_every < 0:
        raise ConfigError("checkpoint_every", f"must be >= 0, got {args.checkpoint_every}")
    check_members_at_once(args.members_at_once)  # before the run folder is made
    if args.compile_cache:
        enable_compile_cache()
    if args.resume is not None:
        config, out = resume_config(args), args.resume
    else:
        config = config_from_args(args)
        out = prepare_out(args.out, config)
    devices = grid_devices(config.grid_size)
    print(f"{'Resuming' if args.resume else 'Training'} {config.grid_size} run(s) of {config.algo} on {config.env} "
          f"({config.num_stages} stages, {config.num_epochs} epochs of {config.steps_per_epoch} steps) on "
          f"{len(devices)} {devices[0].platform} device{'s' * (len(devices) > 1)} -> {out}")
    summary = run(config, out, progress=args.progress, resume=args.resume is not None,
                  checkpoint_every=args.checkpoint_every, tensorboard=args.tensorboard,
                  wandb_project=args.wandb_project, members_at_once=args.members_at_once, devices=devices)
    print(outputs.summary_table(summary))
    print(f"wall time {summary['wall_s']:.0f} s; files in {out}")
    return summary


def cli() -> None:
    """Console entry: bad input ends with one line naming the field, no traceback."""
    try:
        main()
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from None


if __name__ == "__main__":
    cli()
