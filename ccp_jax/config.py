"""One frozen, validated configuration for a whole training grid.

`Config` holds every hyperparameter of SPEC §3 plus the grid (seeds × ratios).
It is checked when it is built, so bad input fails with a message naming the
field before anything is traced or compiled.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from typing import TYPE_CHECKING, Literal, Sequence

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
# The maze kinematics of every run before config.json recorded them (sessions 1-27): reversing, stopping at walls.
LEGACY_MAZE = {"maze_reverse": True, "maze_slide": False}


class ConfigError(ValueError):
    """A configuration value is invalid; the message starts with the field name."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


@dataclasses.dataclass(frozen=True)
class Config:
    """Every resolved field of a run grid. Defaults are the paper's (SPEC §3)."""

    # Task.
    env: str = "maze"
    rooms: int = 2
    # The maze robot's kinematics, which the paper leaves open (envs_mjx.maze.MazeGeometry): whether a[0] < 0
    # drives backwards (else v = (a[0] + 1)/2 v_max, forwards only), and whether a blocked step slides along the wall.
    # A config.json without them is a maze run from before they existed: see LEGACY_MAZE.
    maze_reverse: bool = False
    maze_slide: bool = True
    algo: Algo = "csac"
    # Grid: every ratio vector is trained with every seed, in one vmapped program.
    # A ratio is a number in [0, 1] or "auto" (η* from running critic ranges).
    etas: tuple[tuple[float | str, ...], ...] = ((0.1,),)
    seeds: tuple[int, ...] = (0,)
    # Budget.
    total_steps: int = 3_000_000
    steps_per_epoch: int = 5000
    train_loops_per_epoch: int = 1000
    # An epoch as K cycles of (collect steps/K, then loops/K updates): RLkit's
    # num_train_loops_per_epoch. 1 is the paper's; steps_per_epoch/num_envs is CleanRL's interleaving.
    train_cycles_per_epoch: int = 1
    num_envs: int = 1
    start_steps: int = 1000
    max_episode_steps: int = 1000
    eval_episodes: int = 10
    # SAC.
    hidden: tuple[int, ...] = (256, 256)
    # Initial weights (`networks.MLP`): flax's defaults, or RLkit's (outputs start near 0 everywhere).
    network_init: NetworkInit = "flax"
    batch_size: int = 256
    buffer_size: int = 1_000_000
    gamma: float = 0.95
    tau: float = 0.005
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    alpha_lr: float = 3e-4
    # The entropy each α steers its policy towards; None: −|A| (RLkit's, the paper's).
    target_entropy: float | None = None
    # Every α's value before training (RLkit's: 1, log α = 0).
    initial_alpha: float = 1.0
    # CCP.
    absorbing_success: bool = True
    # Past its stage a subtask's reward is 1 forever, so its critic bootstraps the exact
    # value 1/(1 − γ) there instead of extrapolating into states it never trains on.
    absorbing_stages: bool = True
    normalise_last: bool = False
    # Whose action a' bootstraps a critic target at s' (SPEC §1): "own" is the paper's a' ~ π_n(s')
    # for agent n's batch; "acting" uses π_{n+1} where s' has already entered stage n + 1.
    next_action: NextAction = "own"
    norm_eps: float = 1e-6
    # The tanh correction of log π (`networks.sample_action`): RLkit's capped form or the exact one.
    tanh_log_prob: TanhLogProb = "exact"
    # How Q̂ is scaled: "batch" (the paper: batch min/max), "ema" (running min/max),
    # "floor" (batch min, range at least `norm_floor`, in reward units), "none" (Q̂ = Q: C_n is then the soft
    # value of the cooperative reward η r_n + (1 − η) r_{n+1} under π_n, in reward units, whatever `coop_scale`).
    normaliser: Normaliser = "batch"
    norm_ema_rate: float = 0.005
    norm_floor: float = 1.0
    # Units of the cooperative objective C_n = η Q̂_n + (1 − η) Q̂_{n+1} in the actor loss: "unit" (the
    # paper: C_n in [0, 1]) or "own" (C_n times the own critic's normaliser scale, i.e. Q_n's units), so
    # that α_n weighs entropy against values as Naive's α does, in the actor loss and the critic target alike.
    coop_scale: CoopScale = "unit"
    eta_auto_range: tuple[float, float] = (0.05, 0.95)
    # κ of "auto": η* = Ran(Q_n) / (Ran(Q_n) + κ Ran(Q_{n+1})) recovers Q_n + κ Q_{n+1}; 1 is the appendix's sum.
    eta_auto_next_weight: float = 1.0
    # What "auto" follows: "ranges", the appendix's η* from the critics' running ranges (weighted by κ
    # above), or "outcomes", a controller on where the training episodes fail (`eta.outcome_eta`):
    # each epoch η_n moves by (`eta_auto_up_rate` × episodes failing in stage n − `eta_auto_rate` ×
    # episodes failing in stage n + 1) / episodes entering stage n, from the middle of `eta_auto_range`, within it;
    # or "gated", the same controller with only its upward term until an episode has succeeded in stage n + 1 and
    # only its downward term from then on (a successor that never succeeded says nothing about the handover);
    # or "trusted", as "gated" but with both terms and η_n ≥ the range's middle until that first success.
    eta_auto_rule: EtaAutoRule = "ranges"
    eta_auto_rate: float = 0.05
    # None: the same as `eta_auto_rate`; 0 lets the ratio only fall.
    eta_auto_up_rate: float | None = None
    # The outcome rules' lower bound for agent n: low + n × step (at most the range's middle); 0: low for all.
    eta_auto_floor_step: float = 0.0
    # TP (Transition Policies, Lee et al. 2019; ccp_jax/tp). Primitives: a finished --algo naive run.
    primitives: str | None = None
    primitives_member: int = 0
    tp_max_steps: int = 100  # transition steps before termination is forced
    tp_hidden: tuple[int, ...] = (32, 32)  # tanh policy and value MLPs
    tp_lr: float = 1e-4
    tp_clip: float = 0.2
    tp_value_coef: float = 1.0
    tp_entropy_coef: float = 1e-3
    tp_ppo_epochs: int = 10
    tp_minibatch: int = 64
    tp_gamma: float = 0.99
    tp_gae_lambda: float = 0.98
    tp_delta: float = 0.95  # proximity target of a state t steps before a successful hand-over at T: δ^(T−t)
    tp_prox_hidden: tuple[int, ...] = (96, 96)  # ReLU proximity predictor
    tp_prox_lr: float = 1e-4
    tp_prox_updates: int = 785  # predictor Adam steps per epoch: 5 × (10000 // 64 + 1), as released
    tp_prox_batch: int = 64
    tp_buffer_size: int = 100_000  # per predictor and kind (online success, failure, permanent)
    tp_init_episodes: int = 100  # deterministic primitive episodes for the permanent success states
    tp_init_fraction: float = 0.3  # early fraction of each successful stage kept as permanent successes

    def __post_init__(self) -> None:
        self._validate()

    # ------------------------------------------------------------------ derived
    @property
    def num_stages(self) -> int:
        """Stages N of the task: the maze's rooms, or the env's own fixed count."""
        from ccp_jax.envs import FIXED_STAGES

        return FIXED_STAGES.get(self.env, self.rooms)

    @property
    def num_agents(self) -> int:
        """Agents trained: one per stage, or a single end-to-end agent for SAC."""
        return 1 if self.algo == "sac" else self.num_stages

    @property
    def value_bound(self) -> float:
        """The largest value a critic's rewards allow, r_max / (1 − γ), before any entropy bonus.

        Subtask rewards lie in [0, 1], so r_max is 1 per channel, or N for SAC's summed reward; it is
        also the value a completed subtask bootstraps with (success is absorbing, SPEC §1).
        """
        return (self.num_stages if self.algo == "sac" else 1.0) / (1.0 - self.gamma)

    @property
    def num_epochs(self) -> int:
        return self.total_steps // self.steps_per_epoch

    @property
    def collect_iters(self) -> int:
        """Vectorised env steps per collection cycle (each steps `num_envs` envs)."""
        return self.steps_per_epoch // (self.num_envs * self.train_cycles_per_epoch)

    @property
    def grid(self) -> list[tuple[tuple[float, ...], int]]:
        """Grid members in order: (per-agent eta vector, seed), ratios outermost."""
        return [(self.eta_vector(e), s) for e, s in itertools.product(self.etas, self.seeds)]

    @property
    def grid_size(self) -> int:
        return len(self.etas) * len(self.seeds)

    def eta_vector(self, eta: Sequence[float | str]) -> tuple[float | str, ...]:
        """Per-agent ratios of length `num_agents` (`eta.per_agent`)."""
        from ccp_jax import eta as ratios  # local: eta.py imports this module

        return ratios.per_agent(eta, self.num_agents)

    def grid_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(eta float32[G, num_agents], seed int32[G]) for the vmapped grid axis; "auto" is NaN (`eta.grid_etas`)."""
        from ccp_jax import eta as ratios

        members = self.grid
        seed = np.asarray([m[1] for m in members], np.int32)
        return ratios.grid_etas([m[0] for m in members], self.num_agents), seed

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.update(num_stages=self.num_stages, num_agents=self.num_agents, num_epochs=self.num_epochs, grid_size=self.grid_size)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Config":
        """Inverse of `to_dict` (JSON lists become tuples; derived entries are ignored)."""
        def tupled(x):
            return tuple(tupled(v) for v in x) if isinstance(x, list) else x
        names = {f.name for f in dataclasses.fields(cls)}
        fields = {k: tupled(v) for k, v in d.items() if k in names}
        if fields.get("env", cls.env) == "maze":
            fields = {**LEGACY_MAZE, **fields}
        return cls(**fields)

    def replace(self, **changes) -> "Config":
        return dataclasses.replace(self, **changes)

    def differing(self, other: "Config", ignore: Sequence[str] = ()) -> list[str]:
        """Names of the fields (in declaration order) whose values differ from `other`'s, except `ignore`."""
        return [f.name for f in dataclasses.fields(self)
                if f.name not in ignore and getattr(self, f.name) != getattr(other, f.name)]

    # --------------------------------------------------------------- validation
    def _validate(self) -> None:
        from ccp_jax import eta as ratios  # local: eta.py imports this module
        from ccp_jax.envs import ENV_NAMES  # local: config must not import jax eagerly

        if self.env not in ENV_NAMES and ":" not in self.env:
            raise ConfigError("env", f"unknown env {self.env!r}; choose one of {ENV_NAMES} or 'module.path:factory'")
        if self.algo not in ALGOS:
            raise ConfigError("algo", f"unknown algo {self.algo!r}; choose one of {ALGOS}")
        for name in ("maze_reverse", "maze_slide"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(name, f"must be true or false, got {getattr(self, name)!r}")
            if self.env != "maze" and getattr(self, name) != getattr(Config, name):
                raise ConfigError(name, f"is an option of the maze; env {self.env!r} has no such setting")
        if not isinstance(self.rooms, int) or self.rooms < 2:
            raise ConfigError("rooms", f"must be an integer >= 2, got {self.rooms!r}")
        for name in ("total_steps", "steps_per_epoch", "train_loops_per_epoch", "train_cycles_per_epoch", "num_envs",
                     "max_episode_steps", "eval_episodes", "batch_size", "buffer_size"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value <= 0:
                raise ConfigError(name, f"must be a positive integer, got {value!r}")
        if self.start_steps < 0:
            raise ConfigError("start_steps", f"must be >= 0, got {self.start_steps}")
        if not self.hidden or any(h <= 0 for h in self.hidden):
            raise ConfigError("hidden", f"layer sizes must be positive, got {self.hidden}")
        if self.steps_per_epoch % self.num_envs:
            raise ConfigError("num_envs", f"must divide steps_per_epoch ({self.steps_per_epoch}), got {self.num_envs}")
        cycles = self.train_cycles_per_epoch
        if (self.steps_per_epoch // self.num_envs) % cycles or self.train_loops_per_epoch % cycles:
            raise ConfigError("train_cycles_per_epoch", f"must divide both the epoch's vectorised steps "
                              f"({self.steps_per_epoch // self.num_envs} = steps_per_epoch / num_envs) and "
                              f"train_loops_per_epoch ({self.train_loops_per_epoch}), got {cycles}")
        if self.total_steps < self.steps_per_epoch:
            raise ConfigError("total_steps", f"must be at least one epoch ({self.steps_per_epoch} steps), got {self.total_steps}")
        if self.batch_size > self.buffer_size:
            raise ConfigError("batch_size", f"({self.batch_size}) is larger than buffer_size ({self.buffer_size})")
        if not 0.0 <= self.gamma < 1.0:
            raise ConfigError("gamma", f"must be in [0, 1), got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ConfigError("tau", f"must be in (0, 1], got {self.tau}")
        for name in ("actor_lr", "critic_lr", "alpha_lr", "norm_eps"):
            if getattr(self, name) <= 0:
                raise ConfigError(name, f"must be positive, got {getattr(self, name)}")
        if not self.seeds:
            raise ConfigError("seeds", "at least one seed is needed")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigError("seeds", f"seeds must be distinct, got {self.seeds}")
        ratios.check_ratios(self)
        if self.next_action not in NEXT_ACTIONS:
            raise ConfigError("next_action", f"unknown rule {self.next_action!r}; choose one of {NEXT_ACTIONS}")
        if self.tanh_log_prob not in TANH_LOG_PROBS:
            raise ConfigError("tanh_log_prob", f"unknown form {self.tanh_log_prob!r}; choose one of {TANH_LOG_PROBS}")
        if self.network_init not in NETWORK_INITS:
            raise ConfigError("network_init", f"unknown init {self.network_init!r}; choose one of {NETWORK_INITS}")
        if self.normaliser not in NORMALISERS:
            raise ConfigError("normaliser", f"unknown normaliser {self.normaliser!r}; choose one of {NORMALISERS}")
        if self.coop_scale not in COOP_SCALES:
            raise ConfigError("coop_scale", f"unknown scale {self.coop_scale!r}; choose one of {COOP_SCALES}")
        if not 0.0 < self.norm_ema_rate <= 1.0:
            raise ConfigError("norm_ema_rate", f"must be in (0, 1], got {self.norm_ema_rate}")
        if self.norm_floor <= 0:
            raise ConfigError("norm_floor", f"must be positive, got {self.norm_floor}")
        if self.algo == "tp":
            self._validate_tp()
        if not (math.isfinite(self.initial_alpha) and self.initial_alpha > 0):
            raise ConfigError("initial_alpha", f"must be a positive finite number, got {self.initial_alpha}")
        if self.target_entropy is not None and not math.isfinite(self.target_entropy):
            raise ConfigError("target_entropy", f"must be a finite number (or None for −|A|), got {self.target_entropy}")
        ratios.check_auto(self)

    def _validate_tp(self) -> None:
        if self.primitives is None:
            raise ConfigError("primitives", "--algo tp needs frozen primitives: train them first with --algo naive "
                                            "(same env and rooms), then pass that run folder as --primitives DIR")
        if self.train_cycles_per_epoch != 1:
            raise ConfigError("train_cycles_per_epoch", "tp collects and updates once per epoch; it must be 1")
        for name in ("tp_max_steps", "tp_ppo_epochs", "tp_minibatch", "tp_prox_updates", "tp_buffer_size",
                     "tp_init_episodes", "primitives_member"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < (0 if name == "primitives_member" else 1):
                raise ConfigError(name, f"must be a {'non-negative' if name == 'primitives_member' else 'positive'} "
                                        f"integer, got {value!r}")
        if not isinstance(self.tp_prox_batch, int) or self.tp_prox_batch < 2:
            raise ConfigError("tp_prox_batch", f"must be an integer >= 2 (half online, half permanent), got {self.tp_prox_batch!r}")
        for name in ("tp_hidden", "tp_prox_hidden"):
            if not getattr(self, name) or any(h <= 0 for h in getattr(self, name)):
                raise ConfigError(name, f"layer sizes must be positive, got {getattr(self, name)}")
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


PRESETS: dict[str, dict] = {
    # The paper's hyperparameters (SPEC §3).
    "paper": dict(),
    # SPEC §7's learning yardstick: paper settings with [64, 64] nets and a 2e5 buffer.
    "small": dict(hidden=(64, 64), buffer_size=200_000, total_steps=250_000),
    # Seconds-scale runs for tests.
    "tiny": dict(hidden=(16, 16), batch_size=32, buffer_size=4096, steps_per_epoch=200,
                 train_loops_per_epoch=20, total_steps=400, start_steps=100,
                 max_episode_steps=100, eval_episodes=2, num_envs=2,
                 tp_max_steps=10, tp_hidden=(16, 16), tp_prox_hidden=(16, 16), tp_prox_updates=10,
                 tp_ppo_epochs=2, tp_minibatch=32, tp_buffer_size=1024, tp_init_episodes=4),
}


def make_config(preset: PresetName = "paper", **overrides) -> Config:
    """A `Config` from a named preset, with explicit overrides on top."""
    if preset not in PRESETS:
        raise ConfigError("preset", f"unknown preset {preset!r}; choose one of {tuple(PRESETS)}")
    fields = {f.name for f in dataclasses.fields(Config)}
    unknown = set(overrides) - fields
    if unknown:
        raise ConfigError(sorted(unknown)[0], "not a configuration field")
    return Config(**{**PRESETS[preset], **overrides})
