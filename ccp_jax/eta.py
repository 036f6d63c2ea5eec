"""The cooperative ratio η: how a run gives it, what each agent uses, and how "auto" moves it.

Agent n's actor maximises C_n = η_n Q̂_n + (1 − η_n) Q̂_{n+1} (Eq. (3) of the paper). A run gives η as

- one number shared by the cooperative agents (the paper's main sweep), or one per cooperative agent
  (the paper's independent ratios); the last agent has no next critic and uses η = 1 (`per_agent`);
- "auto" (`AUTO`), estimated while training by one of the rules of `EtaAutoRule`:
  "ranges": η* of the critics' running ranges (Eq. (25), `eta_star`), clipped to `eta_auto_range`, inside
  every update (`actor_eta`); "trusted": once per epoch, from where the training episodes failed
  (`outcome_eta`), starting at the middle of `eta_auto_range` (`initial_auto`).

The grid carries a run's ratios as float32[G, N] with "auto" as NaN (`grid_etas`); the epoch replaces the
NaNs of the outcome rule by its current ratios (`epoch_eta`), the update those of "ranges" (`actor_eta`).
docs/design.md#the-method states η* and the rules.

`Config` parses its ratios here and must load without JAX (`python -m ccp_jax.plot` does not start
it), so the functions that trace import jax.numpy themselves.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Literal, Sequence

import numpy as np

from ccp_jax.config import ConfigError

if TYPE_CHECKING:
    import jax

    from ccp_jax.config import Config

AUTO = "auto"  # a ratio estimated during training, see `EtaAutoRule`
EtaAutoRule = Literal["ranges", "trusted"]
ETA_AUTO_RULES = ("ranges", "trusted")
OUTCOME_RULE = "trusted"  # the rule `outcome_eta` moves, once per epoch from where episodes failed
Ratio = float | str  # a number in [0, 1] or AUTO


# ------------------------------------------------------------------ as given

def parse_eta(text: str, field: str = "eta") -> Ratio:
    """A ratio as typed: '0.3' -> 0.3, 'auto' -> AUTO; ConfigError naming `field` otherwise (`Config` checks the range)."""
    if text.strip() == AUTO:
        return AUTO
    try:
        return float(text)
    except ValueError:
        raise ConfigError(field, f"cannot read {text!r}; a ratio is a number in [0, 1] or {AUTO!r}") from None


def parse_eta_vector(text: str, field: str = "eta_per_agent") -> tuple[Ratio, ...]:
    """'0.1,1.0' -> (0.1, 1.0); 'auto,1' -> ('auto', 1.0)."""
    return tuple(parse_eta(x, field) for x in text.split(","))


def per_agent(eta: Sequence[Ratio], num_agents: int) -> tuple[Ratio, ...]:
    """Per-agent ratios of length `num_agents`.

    A single value is shared by the cooperative agents; N−1 values give one
    per cooperative agent. The last agent gets η = 1 (it has no next critic).
    """
    eta = tuple(x if x == AUTO else float(x) for x in eta)
    n = num_agents
    if len(eta) == 1:
        eta = eta * max(n - 1, 1)
    if len(eta) == n - 1:
        eta = eta + (1.0,)
    return eta[:n]


def grid_etas(vectors: Sequence[Sequence[Ratio]], num_agents: int) -> np.ndarray:
    """Per-agent ratio vectors (`per_agent`'s) as the grid's float32[G, N]; "auto" is NaN."""
    eta = np.asarray([[np.nan if x == AUTO else x for x in v] for v in vectors], np.float32)
    return eta.reshape(len(vectors), num_agents)


# ------------------------------------------------------------ in the update

def eta_star(range_own: jax.Array, range_next: jax.Array, eps: float, next_weight: float = 1.0) -> jax.Array:
    """The ratio that recovers the sum Q_n + κ Q_{n+1}: Ran(Q_n) / (Ran(Q_n) + κ Ran(Q_{n+1})), κ = `next_weight`.

    κ = 1 is the paper's η* (Eq. (25)); κ > 1 weighs the next critic more than the plain sum does.
    Ranges of any shape, elementwise; `eps` keeps two flat critics finite.
    """
    return range_own / (range_own + next_weight * range_next + eps)


def actor_eta(eta: jax.Array, running_own: jax.Array, running_next: jax.Array, cooperative: jax.Array,
              config: Config) -> jax.Array:
    """The η each actor loss uses, float32[N].

    eta float32[N]: the member's ratios, NaN for "auto" (only the "ranges" rule leaves NaNs to the update);
    running_own, running_next float32[N]: the running ranges of each agent's own and next critic;
    cooperative bool[N]: the agents that have a next critic to weigh. "auto" is η* of the running
    ranges with κ = `eta_auto_next_weight`, clipped to `eta_auto_range`; agents without a next critic use 1.
    """
    import jax.numpy as jnp

    auto = jnp.clip(eta_star(running_own, running_next, config.ccp.norm_eps, config.ablations.eta_auto_next_weight),
                    *config.ccp.eta_auto_range)
    return jnp.where(cooperative, jnp.where(jnp.isnan(eta), auto, eta), 1.0)


# ------------------------------------------------------------- in the epoch

def initial_auto(config: Config) -> jax.Array:
    """The outcome rule's ratios before the first epoch, float32[N]: the middle of `eta_auto_range`."""
    import jax.numpy as jnp

    return jnp.full((config.num_agents,), sum(config.ccp.eta_auto_range) / 2, jnp.float32)


def epoch_eta(eta: jax.Array, eta_auto: jax.Array, config: Config) -> jax.Array:
    """The ratios an epoch trains with, float32[N]: under the outcome rule "auto" members (NaN) take `eta_auto`,
    so the learner sees numbers; under "ranges" the NaNs stay for the update to resolve (`actor_eta`)."""
    import jax.numpy as jnp

    if config.ccp.eta_auto_rule != OUTCOME_RULE:
        return eta
    return jnp.where(jnp.isnan(eta), eta_auto, eta)


def next_auto(eta_auto: jax.Array, gate: jax.Array, stages: jax.Array, successes: jax.Array,
              config: Config) -> jax.Array:
    """`eta_auto` float32[N] after an epoch: `outcome_eta` of its training episodes under an outcome rule, else unchanged.

    gate bool[N]: `successor_succeeded`, accumulated over every epoch so far; stages, successes as `outcome_eta`'s.
    """
    if config.ccp.eta_auto_rule != OUTCOME_RULE:
        return eta_auto
    return outcome_eta(eta_auto, stages, successes, config.ccp.eta_auto_rate, config.ccp.eta_auto_range, gate)


def _reached(stages: jax.Array, successes: jax.Array) -> jax.Array:
    """float32[N + 1]: episodes that reached each stage, then those that succeeded ("stage N")."""
    import jax.numpy as jnp

    return jnp.concatenate([stages, successes[None]])


def successor_succeeded(stages: jax.Array, successes: jax.Array, num_agents: int) -> jax.Array:
    """bool[num_agents]: whether any of the epoch's episodes succeeded in stage n + 1 (reached stage n + 2, or
    the goal); False for the last agent, which has no successor, and for SAC's one agent over every stage.
    stages float32[num_stages], successes float32[] as `outcome_eta`'s."""
    import jax.numpy as jnp

    if num_agents == 1:
        return jnp.zeros((1,), bool)
    beyond_next = _reached(stages, successes)[2:]
    return jnp.concatenate([beyond_next > 0, jnp.zeros((1,), bool)])


def outcome_eta(eta: jax.Array, stages: jax.Array, successes: jax.Array, rate: float,
                bounds: tuple[float, float], gate: jax.Array) -> jax.Array:
    """One epoch's move of `--eta auto`'s outcome rule ("trusted"): eta float32[N] -> float32[N].

    stages float32[N]: how many of the epoch's ended training episodes reached each stage; successes
    float32[]: how many succeeded; gate bool[N]: `successor_succeeded`, accumulated over epochs. Of the
    episodes that entered stage n, those that failed in it push η_n up by `rate` each (the agent's own
    subtask is the bottleneck: weigh its own critic more) and those that failed in stage n + 1 push it down
    by `rate` (it hands over where its successor fails: weigh the next critic more), as fractions of the
    episodes that entered stage n; clipped to `bounds`. An agent whose stage no episode entered keeps its η.
    (The last agent's entry moves too but is never used.)

    Which terms apply depends on the gate. Once it is True (stage n + 1 has succeeded at least once), only
    the downward term. Before, both, but η_n is held at or above the middle of `bounds`: a successor that
    has never succeeded is not weighed above the agent's own critic, and an agent that passes its own stage
    every time drifts back to even weighting instead of staying where its early failures pushed it (4 rooms:
    the third agent at 0.95, Naive's greedy door). (The retired "gated" rule applied only the upward term
    before the gate opened: docs/design.md#retired-settings.)
    """
    import jax.numpy as jnp

    reached = _reached(stages, successes)
    entered, failed = reached[:-1], reached[:-1] - reached[1:]
    failed_next = jnp.concatenate([failed[1:], jnp.zeros((1,), failed.dtype)])
    failed = jnp.where(gate, 0.0, failed)
    lower = jnp.where(gate, bounds[0], sum(bounds) / 2)
    moved = eta + (rate * failed - rate * failed_next) / jnp.maximum(entered, 1.0)
    return jnp.clip(jnp.where(entered > 0, moved, eta), lower, bounds[1])
