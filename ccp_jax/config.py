"""One frozen, validated configuration for a whole training grid.

`Config` holds the algorithm and one frozen section per concern: `task`, `grid`, `budget`, `sac`, `ccp`, `tp`
and `ablations` (docs/design.md#configuration). Every setting is declared once, here: its name, type, default
and the docstring under it, which the CLI shows as the flag's help (`ccp_jax.train`). Setting names are unique
across sections, so a setting is named by its flat name everywhere: `make_config(preset, actor_lr=...)`,
`Config.replace(actor_lr=...)`, `Config.differing`, the CLI's `--actor-lr` and every `ConfigError`.

A `Config` is checked when it is built, section by section and then across sections, so bad input fails with a
message naming the field before anything is traced or compiled. config.json holds `to_dict`'s nested form with a
`version`; `migrate` turns every older form into it.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from typing import TYPE_CHECKING, Any, Literal, Mapping, Sequence

import numpy as np

if TYPE_CHECKING:
    from ccp_jax.eta import EtaAutoRule

ALGOS = ("csac", "naive", "sac", "tp")
Algo = Literal["csac", "naive", "sac", "tp"]
PresetName = Literal["paper", "small", "tiny"]
Normaliser = Literal["batch", "ema", "floor", "none"]
NORMALISERS = ("batch", "ema", "floor", "none")
NextAction = Literal["own", "acting"]
NEXT_ACTIONS = ("own", "acting")
TanhLogProb = Literal["rlkit", "exact"]
TANH_LOG_PROBS = ("rlkit", "exact")
NetworkInit = Literal["flax", "rlkit"]
NETWORK_INITS = ("flax", "rlkit")
CoopScale = Literal["unit", "own"]
COOP_SCALES = ("unit", "own")
PegModel = Literal["arm", "hand"]
PEG_MODELS = ("arm", "hand")  # envs_mjx.peg_in_hole.MODELS
PegPhysics = Literal["mjx", "c"]
PEG_PHYSICS = ("mjx", "c")  # envs_mjx.peg_in_hole.PHYSICS
# The maze kinematics of the runs whose config.json predates maze_reverse / maze_slide: a robot that reversed and
# stopped at walls (`migrate`).
LEGACY_MAZE = {"maze_reverse": True, "maze_slide": False}
# The form of config.json `to_dict` writes. 1: every setting at the top level (no "version" key).
VERSION = 2
# Settings that training no longer offers (docs/design.md#retired-settings): a removed setting -> (its section,
# its old default); a remaining setting -> its retired values. A config.json holding a removed setting at its old
# default reads as if it did not; one holding a retired value reads into `Config.retired`, so its run's results
# load, plot and compare, while `Config.check_trainable` refuses to train or resume it.
RETIRED_SETTINGS: dict[str, tuple[str, Any]] = {"eta_auto_up_rate": ("ablations", None),
                                                "eta_auto_floor_step": ("ablations", 0.0)}
RETIRED_VALUES: dict[str, tuple[Any, ...]] = {"eta_auto_rule": ("outcomes", "gated")}


class ConfigError(ValueError):
    """A configuration value is invalid; the message starts with the field name."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


def _positive_ints(section: Any, names: Sequence[str], minimum: int = 1) -> None:
    for name in names:
        value = getattr(section, name)
        if not isinstance(value, (int, np.integer)) or value < minimum:
            kind = "positive" if minimum == 1 else "non-negative" if minimum == 0 else f">= {minimum}"
            raise ConfigError(name, f"must be a {kind} integer, got {value!r}")


def _layers(section: Any, name: str) -> None:
    if not getattr(section, name) or any(h <= 0 for h in getattr(section, name)):
        raise ConfigError(name, f"layer sizes must be positive, got {getattr(section, name)}")


def _choice(section: Any, name: str, choices: Sequence[str], what: str) -> None:
    if getattr(section, name) not in choices:
        raise ConfigError(name, f"unknown {what} {getattr(section, name)!r}; choose one of {tuple(choices)}")


def _finite(section: Any) -> None:
    """Every real number of a section, alone or in a tuple, is finite: nan and inf slip past `<=` checks.

    The grid's ratio vectors (tuples of tuples) are checked with their own rule in `Config._check_ratios`.
    """
    for field in dataclasses.fields(section):
        value = getattr(section, field.name)
        for x in value if isinstance(value, tuple) else (value,):
            if isinstance(x, (float, np.floating)) and not math.isfinite(x):
                raise ConfigError(field.name, f"must be a finite number, got {value!r}")


def _boolean(section: Any, name: str) -> None:
    if not isinstance(getattr(section, name), bool):
        raise ConfigError(name, f"must be true or false, got {getattr(section, name)!r}")


@dataclasses.dataclass(frozen=True)
class Task:
    """The multi-stage task (docs/design.md#environments-and-their-contract)."""

    env: str = "maze"
    """Environment: maze, peg, pusher, or 'module.path:factory' returning an env that meets the contract (check it
    with envs_mjx.contract.check_env)."""
    rooms: int = 2
    """Number of maze rooms (stages). Peg and pusher have 2 stages; a user env sets its own."""
    max_episode_steps: int = 1000
    """Time limit of an episode, in env steps (truncation, not a termination)."""
    peg_model: PegModel = "arm"
    """Peg: the robot that does the task, arm (the Panda arm with the Franka Hand, IK-controlled) or hand (the
    Franka Hand alone on a slide along x: same scene, contacts, actions, observations and rewards; 1.6-2.5x
    faster on a CPU; docs/peg.md#the-hand-variant)."""
    peg_physics: PegPhysics = "mjx"
    """Peg: what steps the physics, mjx (MuJoCo MJX, inside the compiled program on any JAX device) or c (C MuJoCo
    on the host CPU behind a JAX callback: the same task, 5-13x faster on a CPU; docs/peg.md#c-physics)."""

    def check(self) -> None:
        from ccp_jax.envs import ENV_NAMES  # local: config must not import jax eagerly

        if self.env not in ENV_NAMES and ":" not in self.env:
            raise ConfigError("env", f"unknown env {self.env!r}; choose one of {ENV_NAMES} or 'module.path:factory'")
        _choice(self, "peg_model", PEG_MODELS, "peg model")
        _choice(self, "peg_physics", PEG_PHYSICS, "peg physics")
        if not isinstance(self.rooms, int) or self.rooms < 2:
            raise ConfigError("rooms", f"must be an integer >= 2, got {self.rooms!r}")
        _positive_ints(self, ("max_episode_steps",))


@dataclasses.dataclass(frozen=True)
class Grid:
    """The runs trained together in one vmapped program: every ratio vector with every seed, ratios outermost."""

    etas: tuple[tuple[float | str, ...], ...] = ((0.1,),)
    """Ratio vectors: one value shared by the cooperative agents, or one per cooperative agent; each a number in
    [0, 1] or "auto" (`ccp_jax.eta`). The CLI gives them as --eta or --eta-per-agent."""
    seeds: tuple[int, ...] = (0,)
    """Seeds, distinct. The CLI gives them as --seeds K --first-seed S."""

    def check(self) -> None:
        if not self.seeds:
            raise ConfigError("seeds", "at least one seed is needed")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigError("seeds", f"seeds must be distinct, got {self.seeds}")


@dataclasses.dataclass(frozen=True)
class Budget:
    """How long a run trains and how its epochs are made (docs/design.md#hyperparameters)."""

    total_steps: int = 3_000_000
    """Environment steps per run. May be raised when resuming."""
    steps_per_epoch: int = 5000
    """Environment steps per epoch, over all parallel envs."""
    train_loops_per_epoch: int = 1000
    """Joint updates of every agent per epoch."""
    start_steps: int = 1000
    """Uniform-random env steps before the policies act."""
    num_envs: int = 1
    """Environments stepped in parallel per run; must divide steps_per_epoch."""
    eval_episodes: int = 10
    """Deterministic evaluation episodes after every epoch."""

    def check(self) -> None:
        _positive_ints(self, ("total_steps", "steps_per_epoch", "train_loops_per_epoch", "num_envs", "eval_episodes"))
        if self.start_steps < 0:
            raise ConfigError("start_steps", f"must be >= 0, got {self.start_steps}")
        if self.steps_per_epoch % self.num_envs:
            raise ConfigError("num_envs", f"must divide steps_per_epoch ({self.steps_per_epoch}), got {self.num_envs}")
        if self.total_steps < self.steps_per_epoch:
            raise ConfigError("total_steps", f"must be at least one epoch ({self.steps_per_epoch} steps), "
                                             f"got {self.total_steps}")
        if self.total_steps % self.steps_per_epoch:  # else the last part-epoch would silently not be trained
            lower = self.total_steps - self.total_steps % self.steps_per_epoch
            raise ConfigError("total_steps", f"must be a whole number of epochs of {self.steps_per_epoch} steps, got "
                                             f"{self.total_steps}: use {lower} or {lower + self.steps_per_epoch}")


@dataclasses.dataclass(frozen=True)
class Sac:
    """Every agent's SAC: networks, replay, optimisers, temperature (RLkit's, the paper's)."""

    hidden: tuple[int, ...] = (256, 256)
    """Hidden layer sizes of the actor and the critics (ReLU)."""
    batch_size: int = 256
    """Transitions per update and agent."""
    buffer_size: int = 1_000_000
    """Replay buffer capacity per agent."""
    gamma: float = 0.95
    """Discount factor γ (the paper warns against larger)."""
    tau: float = 0.005
    """Polyak rate of the target critics."""
    actor_lr: float = 3e-4
    """Adam learning rate of the actors."""
    critic_lr: float = 3e-4
    """Adam learning rate of the critics."""
    alpha_lr: float = 3e-4
    """Adam learning rate of the temperatures α."""
    target_entropy: float | None = None
    """Entropy the temperatures α steer the policies towards; None: −|A|, the action size negated (RLkit's)."""
    initial_alpha: float = 1.0
    """Every temperature α before training (RLkit's: 1, log α = 0)."""

    def check(self) -> None:
        _layers(self, "hidden")
        _positive_ints(self, ("batch_size", "buffer_size"))
        if self.batch_size > self.buffer_size:
            raise ConfigError("batch_size", f"({self.batch_size}) is larger than buffer_size ({self.buffer_size})")
        if not 0.0 <= self.gamma < 1.0:
            raise ConfigError("gamma", f"must be in [0, 1), got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ConfigError("tau", f"must be in (0, 1], got {self.tau}")
        for name in ("actor_lr", "critic_lr", "alpha_lr"):
            if getattr(self, name) <= 0:
                raise ConfigError(name, f"must be positive, got {getattr(self, name)}")
        if not (math.isfinite(self.initial_alpha) and self.initial_alpha > 0):
            raise ConfigError("initial_alpha", f"must be a positive finite number, got {self.initial_alpha}")
        if self.target_entropy is not None and not math.isfinite(self.target_entropy):
            raise ConfigError("target_entropy", f"must be a finite number (or None for −|A|), got {self.target_entropy}")


@dataclasses.dataclass(frozen=True)
class Ccp:
    """The cooperative method: absorbing values, the normaliser's ε and running ranges, and the "auto" ratio
    (docs/design.md#the-method, docs/design.md#decisions-the-paper-leaves-open)."""

    absorbing_success: bool = True
    """Success bootstraps the absorbing value of all-ones rewards, 1/(1 − γ) per channel; off: success ends with
    value 0."""
    absorbing_stages: bool = True
    """Past its stage a subtask's reward is 1 forever, so critic n bootstraps the exact value 1/(1 − γ) there
    instead of extrapolating into states it never trains on; off: the paper's literal Algorithm 2."""
    norm_eps: float = 1e-6
    """ε of the normaliser Q̂ = (Q − min) / (max − min + ε), and of η*."""
    norm_ema_rate: float = 0.005
    """Rate of every critic's running (EMA) min and max: the ranges the ranges rule of --eta auto reads, and the
    bounds of --normaliser ema."""
    eta_auto_rule: EtaAutoRule = "ranges"
    """What --eta auto follows: ranges (the appendix's η* of the critics' running ranges), or trusted: once per
    epoch, from where the training episodes failed (until stage n + 1 has seen a success, η_n moves up with those
    failing in stage n and down with those failing in stage n + 1, at least mid-range; after it, only down).
    docs/design.md#the-method."""
    eta_auto_range: tuple[float, float] = (0.05, 0.95)
    """--eta auto: the interval the ratio stays in."""
    eta_auto_rate: float = 0.05
    """--eta auto under the trusted rule: η's largest move per epoch."""
    pbt_every: int = 0
    """Population-based training of the ratios (docs/pbt.md): every K epochs the grid's members are ranked by the
    fitness of their training episodes since the last ranking, and each of the bottom pbt_fraction copies the
    whole state of a random one of the top pbt_fraction (where that one is fitter) and perturbs its ratios; the
    grid's ratios are the starting population. 0: off, every member keeps its ratios."""
    pbt_fraction: float = 0.25
    """PBT: the fraction of the members replaced at each ranking (at least one), and the fraction they copy from;
    in (0, 0.5]."""
    pbt_factors: tuple[float, float] = (0.8, 1.25)
    """PBT: a copied member's ratios are each multiplied by one of these (chosen at random per cooperative agent),
    then clipped to [0, 1]."""
    pbt_resample: float = 0.25
    """PBT: the probability that a copied member's ratio is instead drawn anew, uniformly in [0, 1] (per
    cooperative agent)."""

    def check(self) -> None:
        from ccp_jax.eta import ETA_AUTO_RULES  # local: eta.py imports this module

        _boolean(self, "absorbing_success")
        _boolean(self, "absorbing_stages")
        if self.norm_eps <= 0:
            raise ConfigError("norm_eps", f"must be positive, got {self.norm_eps}")
        if not 0.0 < self.norm_ema_rate <= 1.0:
            raise ConfigError("norm_ema_rate", f"must be in (0, 1], got {self.norm_ema_rate}")
        _choice(self, "eta_auto_rule", ETA_AUTO_RULES, "rule")
        if not (math.isfinite(self.eta_auto_rate) and 0.0 < self.eta_auto_rate <= 1.0):
            raise ConfigError("eta_auto_rate", f"must be in (0, 1], got {self.eta_auto_rate}")
        lo, hi = self.eta_auto_range
        if not 0.0 <= lo <= hi <= 1.0:
            raise ConfigError("eta_auto_range", f"must satisfy 0 <= low <= high <= 1, got {self.eta_auto_range}")
        _positive_ints(self, ("pbt_every",), minimum=0)
        if not (math.isfinite(self.pbt_fraction) and 0.0 < self.pbt_fraction <= 0.5):
            raise ConfigError("pbt_fraction", f"must be in (0, 0.5] (the bottom and the top fraction must not "
                                              f"overlap), got {self.pbt_fraction}")
        if len(self.pbt_factors) != 2 or not all(math.isfinite(f) and f > 0 for f in self.pbt_factors):
            raise ConfigError("pbt_factors", f"must be two positive finite numbers, got {self.pbt_factors}")
        if not (math.isfinite(self.pbt_resample) and 0.0 <= self.pbt_resample <= 1.0):
            raise ConfigError("pbt_resample", f"must be in [0, 1], got {self.pbt_resample}")


@dataclasses.dataclass(frozen=True)
class Tp:
    """The Transition Policies baseline, --algo tp (Lee et al. 2019; docs/tp.md): PPO transition policies between
    frozen primitives, rewarded by proximity predictors."""

    primitives: str | None = None
    """Run folder of a finished --algo naive run (same env and rooms) whose agents are the frozen primitives."""
    primitives_member: int = 0
    """Which grid member of the --primitives run supplies the primitives."""
    tp_max_steps: int = 100
    """Transition steps before termination is forced."""
    tp_hidden: tuple[int, ...] = (32, 32)
    """Hidden layer sizes of the tanh transition policy and value networks."""
    tp_lr: float = 1e-4
    """Adam learning rate of the transition policies and values."""
    tp_clip: float = 0.2
    """PPO's clipping ε."""
    tp_value_coef: float = 1.0
    """Weight of the value loss."""
    tp_entropy_coef: float = 1e-3
    """Weight of the entropy bonus."""
    tp_ppo_epochs: int = 10
    """PPO passes over each epoch's transitions."""
    tp_minibatch: int = 64
    """PPO minibatch size."""
    tp_gamma: float = 0.99
    """Discount of the proximity reward."""
    tp_gae_lambda: float = 0.98
    """GAE's λ."""
    tp_delta: float = 0.95
    """Proximity target of a state t steps before a successful handover at T: δ^(T−t)."""
    tp_prox_hidden: tuple[int, ...] = (96, 96)
    """Hidden layer sizes of the proximity predictors (ReLU)."""
    tp_prox_lr: float = 1e-4
    """Adam learning rate of the proximity predictors."""
    tp_prox_updates: int = 785
    """Proximity-predictor Adam steps per epoch: 5 × (10000 // 64 + 1), as released."""
    tp_prox_batch: int = 64
    """Proximity-predictor batch: half online, half permanent states."""
    tp_buffer_size: int = 100_000
    """Capacity per predictor and kind (online success, failure, permanent)."""
    tp_init_episodes: int = 100
    """Deterministic primitive episodes that seed the permanent success states."""
    tp_init_fraction: float = 0.3
    """Early fraction of each successful stage kept as permanent successes."""

    def check(self) -> None:
        _positive_ints(self, ("tp_max_steps", "tp_ppo_epochs", "tp_minibatch", "tp_prox_updates", "tp_buffer_size",
                              "tp_init_episodes"))
        _positive_ints(self, ("primitives_member",), minimum=0)
        if not isinstance(self.tp_prox_batch, int) or self.tp_prox_batch < 2:
            raise ConfigError("tp_prox_batch", f"must be an integer >= 2 (half online, half permanent), "
                                               f"got {self.tp_prox_batch!r}")
        _layers(self, "tp_hidden")
        _layers(self, "tp_prox_hidden")
        for name in ("tp_lr", "tp_prox_lr", "tp_clip"):
            if getattr(self, name) <= 0:
                raise ConfigError(name, f"must be positive, got {getattr(self, name)}")
        for name in ("tp_value_coef", "tp_entropy_coef"):
            if getattr(self, name) < 0:
                raise ConfigError(name, f"must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.tp_gamma < 1.0:
            raise ConfigError("tp_gamma", f"must be in [0, 1), got {self.tp_gamma}")
        if not 0.0 <= self.tp_gae_lambda <= 1.0:
            raise ConfigError("tp_gae_lambda", f"must be in [0, 1], got {self.tp_gae_lambda}")
        if not 0.0 < self.tp_delta < 1.0:
            raise ConfigError("tp_delta", f"must be in (0, 1), got {self.tp_delta}")
        if not 0.0 < self.tp_init_fraction <= 1.0:
            raise ConfigError("tp_init_fraction", f"must be in (0, 1], got {self.tp_init_fraction}")


@dataclasses.dataclass(frozen=True)
class Ablations:
    """Settings whose study is concluded: the default is the chosen variant, the others reproduce the evidence
    (docs/design.md#configuration)."""

    maze_reverse: bool = False
    """Maze: a[0] < 0 drives the robot backwards (v = a[0] v_max); off: forwards only, v = (a[0] + 1)/2 v_max."""
    maze_slide: bool = True
    """Maze: a step blocked by a wall slides along it for the rest of the step; off: it stops there."""
    peg_grip_held: bool = False
    """Peg: from the hand-over on, the gripper stays closed whatever the insertion agent commands, so the first
    agent's grasp decides insertability (no regrasp). Not the paper's task: a diagnostic (docs/peg.md)."""
    network_init: NetworkInit = "flax"
    """Initial weights: flax (lecun-normal kernels, zero biases) or rlkit (RLkit's SAC: fan-in uniform hidden
    layers, last layers U(±3e-3) critic and U(±1e-3) actor, so every output starts near 0)."""
    tanh_log_prob: TanhLogProb = "exact"
    """The tanh correction of log π: exact, or rlkit (RLkit's log(1 − tanh² + 1e-6), capped at saturation)."""
    next_action: NextAction = "own"
    """Whose action a' bootstraps a critic target at s': own (the paper's a' ~ π_n(s') for agent n's batch) or
    acting (π_{n+1} where s' has already entered stage n + 1)."""
    normalise_last: bool = False
    """The last agent's actor uses its normalised critic (η_N = 1 on Q̂_N) instead of the plain SAC actor loss."""
    coop_scale: CoopScale = "unit"
    """Units of the cooperative objective C_n = η Q̂_n + (1 − η) Q̂_{n+1} in the actor loss: unit (the paper's,
    C_n in [0, 1]) or own (C_n times the own critic's normaliser scale, Q_n's units, so that α_n weighs entropy
    against values as Naive's α does; η = 1 is Naive)."""
    normaliser: Normaliser = "batch"
    """How critics are scaled in the actor loss: batch (the paper's batch min/max), ema (running min/max), floor
    (batch min, range at least norm_floor reward units), none (Q̂ = Q: C_n is the soft value of the cooperative
    reward η r_n + (1 − η) r_{n+1} in reward units, whatever coop_scale)."""
    norm_floor: float = 1.0
    """Smallest range the floor normaliser divides by, in reward units."""
    eta_auto_next_weight: float = 1.0
    """--eta auto under the ranges rule: κ in η* = Ran(Q_n) / (Ran(Q_n) + κ Ran(Q_{n+1})), the ratio whose
    objective is Q_n + κ Q_{n+1}; 1 is the appendix's sum."""
    train_cycles_per_epoch: int = 1
    """Split each epoch into K cycles of (collect steps/K, then updates/K): RLkit's num_train_loops_per_epoch.
    1 is the paper's order; steps_per_epoch/num_envs interleaves like CleanRL."""

    def check(self) -> None:
        _boolean(self, "maze_reverse")
        _boolean(self, "maze_slide")
        _boolean(self, "peg_grip_held")
        _choice(self, "network_init", NETWORK_INITS, "init")
        _choice(self, "tanh_log_prob", TANH_LOG_PROBS, "form")
        _choice(self, "next_action", NEXT_ACTIONS, "rule")
        _boolean(self, "normalise_last")
        _choice(self, "coop_scale", COOP_SCALES, "scale")
        _choice(self, "normaliser", NORMALISERS, "normaliser")
        if self.norm_floor <= 0:
            raise ConfigError("norm_floor", f"must be positive, got {self.norm_floor}")
        if not (math.isfinite(self.eta_auto_next_weight) and self.eta_auto_next_weight > 0):
            raise ConfigError("eta_auto_next_weight", f"must be a positive finite number, got {self.eta_auto_next_weight}")
        _positive_ints(self, ("train_cycles_per_epoch",))


# Section name -> its dataclass, in the order of `Config`'s fields (and of `Config.flat`).
SECTIONS: dict[str, type] = {"task": Task, "grid": Grid, "budget": Budget, "sac": Sac, "ccp": Ccp, "tp": Tp,
                             "ablations": Ablations}
# Flat setting name -> the section that holds it (None: `Config` itself).
# The settings only one built-in env reads, by env.
ENV_OPTIONS = {"maze": ("maze_reverse", "maze_slide"), "peg": ("peg_model", "peg_physics", "peg_grip_held")}
SECTION_OF: dict[str, str | None] = {"algo": None, **{f.name: section for section, cls in SECTIONS.items()
                                                      for f in dataclasses.fields(cls)}}


@dataclasses.dataclass(frozen=True)
class Config:
    """Every setting of a run grid, in sections. Defaults are the paper's (docs/design.md#hyperparameters)."""

    algo: Algo = "csac"
    """csac: cooperative agents; naive: independent agents; sac: one end-to-end agent; tp: transition policies
    between frozen primitives (needs --primitives)."""
    task: Task = Task()
    grid: Grid = Grid()
    budget: Budget = Budget()
    sac: Sac = Sac()
    ccp: Ccp = Ccp()
    tp: Tp = Tp()
    ablations: Ablations = Ablations()
    retired: tuple[tuple[str, Any], ...] = ()
    """(name, value) of each retired setting (`RETIRED_SETTINGS`, `RETIRED_VALUES`) that the config.json this was
    read from holds, in name order; the section keeps the default where the setting remains. Empty for every
    config that can train (`check_trainable`)."""

    def __post_init__(self) -> None:
        for name, cls in SECTIONS.items():
            if not isinstance(getattr(self, name), cls):
                raise ConfigError(name, f"must be a {cls.__name__} section, got {getattr(self, name)!r}")
        for entry in self.retired:
            if not (isinstance(entry, tuple) and len(entry) == 2
                    and (entry[0] in RETIRED_SETTINGS or entry[1] in RETIRED_VALUES.get(entry[0], ()))):
                raise ConfigError("retired", f"must hold (name, value) pairs of retired settings, got {entry!r}")
        self._check()

    def check_trainable(self) -> None:
        """Refuses, naming the setting, a config read from a run that used a retired setting."""
        if self.retired:
            name, value = self.retired[0]
            raise ConfigError(name, f"{value!r} is retired (docs/design.md#retired-settings): the run's results "
                                    "still read, plot and compare, but it cannot train or resume")

    # ------------------------------------------------------------------ derived
    @property
    def num_stages(self) -> int:
        """Stages N of the task: the maze's rooms, or the env's own fixed count."""
        from ccp_jax.envs import FIXED_STAGES

        return FIXED_STAGES.get(self.task.env, self.task.rooms)

    @property
    def num_agents(self) -> int:
        """Agents trained: one per stage, or a single end-to-end agent for SAC."""
        return 1 if self.algo == "sac" else self.num_stages

    @property
    def value_bound(self) -> float:
        """The largest value a critic's rewards allow, r_max / (1 − γ), before any entropy bonus.

        Subtask rewards lie in [0, 1], so r_max is 1 per channel, or N for SAC's summed reward; it is
        also the value a completed subtask bootstraps with (success is absorbing, docs/design.md#the-method).
        """
        return (self.num_stages if self.algo == "sac" else 1.0) / (1.0 - self.sac.gamma)

    @property
    def num_epochs(self) -> int:
        return self.budget.total_steps // self.budget.steps_per_epoch

    @property
    def collect_iters(self) -> int:
        """Vectorised env steps per collection cycle (each steps `num_envs` envs)."""
        return self.budget.steps_per_epoch // (self.budget.num_envs * self.ablations.train_cycles_per_epoch)

    @property
    def members(self) -> list[tuple[tuple[float | str, ...], int]]:
        """Grid members in order: (per-agent eta vector, seed), ratios outermost."""
        return [(self.eta_vector(e), s) for e, s in itertools.product(self.grid.etas, self.grid.seeds)]

    @property
    def grid_size(self) -> int:
        return len(self.grid.etas) * len(self.grid.seeds)

    def eta_vector(self, eta: Sequence[float | str]) -> tuple[float | str, ...]:
        """Per-agent ratios of length `num_agents` (`eta.per_agent`)."""
        from ccp_jax import eta as ratios  # local: eta.py imports this module

        return ratios.per_agent(eta, self.num_agents)

    def grid_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(eta float32[G, num_agents], seed int32[G]) for the vmapped grid axis; "auto" is NaN (`eta.grid_etas`)."""
        from ccp_jax import eta as ratios

        members = self.members
        seed = np.asarray([m[1] for m in members], np.int32)
        return ratios.grid_etas([m[0] for m in members], self.num_agents), seed

    # ------------------------------------------------------------ flat names
    def flat(self) -> dict[str, Any]:
        """Every setting by its flat name, in declaration order (`SECTION_OF`)."""
        return {name: self._get(name) for name in SECTION_OF}

    def _get(self, name: str) -> Any:
        section = SECTION_OF[name]
        return getattr(self if section is None else getattr(self, section), name)

    @classmethod
    def from_flat(cls, fields: Mapping[str, Any]) -> "Config":
        """A `Config` from settings by flat name; the others keep their defaults."""
        return cls._build(None, fields)

    def replace(self, **changes) -> "Config":
        """A copy with `changes`, each a setting's flat name (or a whole section by its name)."""
        return self._build(self, changes)

    @classmethod
    def _build(cls, base: "Config | None", changes: Mapping[str, Any]) -> "Config":
        """`base` (None: the defaults) with `changes`, each a flat name or a section."""
        top: dict[str, Any] = {}
        sections: dict[str, dict[str, Any]] = {}
        for name, value in changes.items():
            if name in SECTIONS or name in ("algo", "retired"):
                top[name] = value
            elif name in SECTION_OF:
                sections.setdefault(SECTION_OF[name], {})[name] = value
            else:
                raise ConfigError(name, "not a configuration field")
        for section, values in sections.items():
            if section in top:
                top[section] = dataclasses.replace(top[section], **values)
            elif base is None:
                top[section] = SECTIONS[section](**values)
            else:
                top[section] = dataclasses.replace(getattr(base, section), **values)
        return cls(**top) if base is None else dataclasses.replace(base, **top)

    def differing(self, other: "Config", ignore: Sequence[str] = ()) -> list[str]:
        """Flat names of the settings (in declaration order) whose values differ from `other`'s, except `ignore`."""
        names = [name for name in SECTION_OF if name not in ignore and self._get(name) != other._get(name)]
        return names + (["retired"] if "retired" not in ignore and self.retired != other.retired else [])

    # ------------------------------------------------------------- config.json
    def to_dict(self) -> dict:
        """The nested form config.json holds: `version`, `algo`, one object per section, then derived values."""
        return {"version": VERSION, "algo": self.algo,
                **{name: dataclasses.asdict(getattr(self, name)) for name in SECTIONS},
                **({"retired": dict(self.retired)} if self.retired else {}),
                "num_stages": self.num_stages, "num_agents": self.num_agents, "num_epochs": self.num_epochs,
                "grid_size": self.grid_size}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Config":
        """The `Config` of a config.json of any version (`migrate`); JSON lists become tuples."""
        d = migrate(d)

        def tupled(x):
            return tuple(tupled(v) for v in x) if isinstance(x, list) else x

        fields: dict[str, Any] = {"algo": d["algo"]} if "algo" in d else {}
        if d.get("retired"):
            fields["retired"] = tuple(sorted((name, tupled(value)) for name, value in d["retired"].items()))
        for name, section in SECTIONS.items():
            values = d.get(name, {})
            if not isinstance(values, Mapping):
                raise TypeError(f"section {name!r} must be an object, got {values!r}")
            unknown = set(values) - {f.name for f in dataclasses.fields(section)}
            if unknown:
                raise TypeError(f"section {name!r} has no setting {sorted(unknown)[0]!r}")
            fields.update({k: tupled(v) for k, v in values.items()})
        return cls.from_flat(fields)

    # --------------------------------------------------------------- validation
    def _check(self) -> None:
        """Each section's own checks, then those across sections."""
        for name in SECTIONS:
            _finite(getattr(self, name))
        self.task.check()
        _choice(self, "algo", ALGOS, "algo")
        self.grid.check()
        self.budget.check()
        self.sac.check()
        self.ccp.check()
        self.ablations.check()
        self._check_env_options()
        self._check_cycles()
        self._check_ratios()
        self._check_pbt()
        if self.algo == "tp":
            self.tp.check()
            self._check_tp()

    def _check_env_options(self) -> None:
        """Settings of one built-in env are refused at their non-default values for another env."""
        for env, names in ENV_OPTIONS.items():
            for name in names:
                if self.task.env != env and self._get(name) != getattr(SECTIONS[SECTION_OF[name]], name):
                    raise ConfigError(name, f"is an option of {env}; env {self.task.env!r} has no such setting")

    def _check_cycles(self) -> None:
        budget, cycles = self.budget, self.ablations.train_cycles_per_epoch
        if (budget.steps_per_epoch // budget.num_envs) % cycles or budget.train_loops_per_epoch % cycles:
            raise ConfigError("train_cycles_per_epoch", f"must divide both the epoch's vectorised steps "
                              f"({budget.steps_per_epoch // budget.num_envs} = steps_per_epoch / num_envs) and "
                              f"train_loops_per_epoch ({budget.train_loops_per_epoch}), got {cycles}")

    def _check_ratios(self) -> None:
        """A grid of distinct, well-formed ratio vectors for the agents (`eta.per_agent` reads them)."""
        from ccp_jax.eta import AUTO, per_agent  # local: eta.py imports this module

        etas, n = self.grid.etas, self.num_agents
        if not etas:
            raise ConfigError("eta", "at least one ratio is needed")
        if self.algo != "csac" and len(etas) > 1:
            raise ConfigError("eta", f"--algo {self.algo} trains every agent on its own critic alone (η = 1): a grid "
                                     f"of ratios would train identical runs; leave --eta out "
                                     f"(got {[list(e) for e in etas]})")
        for eta in etas:
            if len(eta) not in (1, n - 1, n) or (len(eta) == n and n > 1 and not self.ablations.normalise_last):
                allowed = "1 value" if n <= 2 else f"1 value or {n - 1} values (one per cooperative agent)"
                raise ConfigError("eta_per_agent", f"ratio vector {tuple(eta)} has {len(eta)} values; "
                                  f"{n} agent{'s' if n > 1 else ''} need{'' if n > 1 else 's'} {allowed}")
            for x in eta:
                if x != AUTO and not (isinstance(x, (int, float)) and 0.0 <= float(x) <= 1.0):
                    raise ConfigError("eta", f"ratios must be numbers in [0, 1] or {AUTO!r}, got {x!r}")
        vectors = [per_agent(e, n) for e in etas]
        if len(set(vectors)) != len(vectors):  # with the same seeds, a repeated ratio trains identical runs
            raise ConfigError("eta", f"ratios must be distinct, got {[list(e) for e in etas]}")

    def _check_pbt(self) -> None:
        """PBT moves the numeric ratios of a cooperative population of at least two members."""
        from ccp_jax.eta import AUTO  # local: eta.py imports this module

        if not self.ccp.pbt_every:
            for name in ("pbt_fraction", "pbt_factors", "pbt_resample"):
                if getattr(self.ccp, name) != getattr(Ccp, name):
                    raise ConfigError(name, "is a setting of population-based training; turn it on with --pbt-every K")
            return
        if self.algo != "csac":
            raise ConfigError("pbt_every", f"population-based training moves the cooperative ratios of csac; "
                                           f"--algo {self.algo} has none")
        if self.grid_size < 2:
            raise ConfigError("pbt_every", "population-based training needs at least 2 members (--eta with several "
                                           f"ratios and/or --seeds K), got {self.grid_size}")
        if any(x == AUTO for eta in self.grid.etas for x in eta):
            raise ConfigError("pbt_every", "population-based training moves numeric ratios; the starting ratios "
                                           f"must not be {AUTO!r}, got {[list(e) for e in self.grid.etas]}")

    def _check_tp(self) -> None:
        if self.tp.primitives is None:
            raise ConfigError("primitives", "--algo tp needs frozen primitives: train them first with --algo naive "
                                            "(same env and rooms), then pass that run folder as --primitives DIR")
        if self.ablations.train_cycles_per_epoch != 1:
            raise ConfigError("train_cycles_per_epoch", "tp collects and updates once per epoch; it must be 1")


def migrate(d: Mapping[str, Any]) -> dict:
    """A config.json's contents of any version in the current nested form (`Config.to_dict`'s).

    Version 1 (no "version" key) holds every setting at the top level, with the settings of its time: a missing
    one takes its default, except a maze run's kinematics, which predate maze_reverse / maze_slide and were
    `LEGACY_MAZE`'s robot. Derived values (num_stages, ...) and unknown top-level keys are dropped. Retired
    settings leave their sections (`_retire`).
    """
    version = d.get("version", 1)
    if not isinstance(version, int) or not 1 <= version <= VERSION:
        newer = "; a newer ccp-jax wrote it" if isinstance(version, int) and version > VERSION else ""
        raise ConfigError("version", f"config.json version {version!r} is not one this ccp-jax reads "
                                     f"(1..{VERSION}){newer}")
    if version == 1:
        flat = {k: v for k, v in d.items() if k in SECTION_OF or k in RETIRED_SETTINGS}
        if flat.get("env", Task.env) == "maze":
            flat = {**LEGACY_MAZE, **flat}
        nested: dict[str, Any] = {"version": VERSION}
        if "algo" in flat:
            nested["algo"] = flat.pop("algo")
        for name, value in flat.items():
            nested.setdefault(RETIRED_SETTINGS[name][0] if name in RETIRED_SETTINGS else SECTION_OF[name], {})[name] = value
        return _retire(nested)
    return _retire({k: v for k, v in d.items() if k in ("version", "algo", "retired") or k in SECTIONS})


def _retire(nested: dict[str, Any]) -> dict[str, Any]:
    """`nested` with the retired settings out of its sections: dropped at their old default, else under "retired"."""
    retired = dict(nested.get("retired") or {})
    sections = {name: dict(values) if isinstance(values, Mapping) else values
                for name, values in nested.items() if name in SECTIONS}
    for name, (section, old_default) in RETIRED_SETTINGS.items():
        values = sections.get(section)
        if isinstance(values, dict) and name in values and (value := values.pop(name)) != old_default:
            retired[name] = value
    for name, values in RETIRED_VALUES.items():
        section = sections.get(SECTION_OF[name])
        if isinstance(section, dict) and section.get(name) in values:
            retired[name] = section.pop(name)
    return {**nested, **sections, **({"retired": retired} if retired else {})}


PRESETS: dict[str, dict] = {
    # The paper's hyperparameters (docs/design.md#hyperparameters).
    "paper": dict(),
    # The learning yardstick's sizes (docs/design.md#the-learning-yardstick): [64, 64] nets and a 2e5 buffer.
    "small": dict(hidden=(64, 64), buffer_size=200_000, total_steps=250_000),
    # Seconds-scale runs for tests.
    "tiny": dict(hidden=(16, 16), batch_size=32, buffer_size=4096, steps_per_epoch=200,
                 train_loops_per_epoch=20, total_steps=400, start_steps=100,
                 max_episode_steps=100, eval_episodes=2, num_envs=2,
                 tp_max_steps=10, tp_hidden=(16, 16), tp_prox_hidden=(16, 16), tp_prox_updates=10,
                 tp_ppo_epochs=2, tp_minibatch=32, tp_buffer_size=1024, tp_init_episodes=4),
}


def preset_settings(preset: str) -> dict[str, Any]:
    """Every setting of a preset by flat name, unchecked (the CLI shows them as its defaults)."""
    if preset not in PRESETS:
        raise ConfigError("preset", f"unknown preset {preset!r}; choose one of {tuple(PRESETS)}")
    defaults = {"algo": Config.algo, **{f.name: f.default for cls in SECTIONS.values() for f in dataclasses.fields(cls)}}
    return {**defaults, **PRESETS[preset]}


def make_config(preset: PresetName = "paper", **overrides) -> Config:
    """A `Config` from a named preset, with explicit overrides (flat names) on top."""
    settings = preset_settings(preset)  # refuses an unknown preset
    unknown = set(overrides) - set(SECTION_OF)
    if unknown:
        raise ConfigError(sorted(unknown)[0], "not a configuration field")
    return Config.from_flat({**settings, **overrides})
