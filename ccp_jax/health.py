"""When a grid member has diverged: one rule, applied inside the compiled epoch (`diverged`, which freezes the
member) and to the rows written from it (`outputs.divergence`, which says why).

Diverged, per epoch (the epoch's update metrics, means over its updates, per agent):
  * a critic above `DIVERGED` × the value bound its rewards allow (`Config.value_bound`): its entropy bonus
    adds at most α |A| log 2 / (1 − γ) (no distribution on [−1, 1]^|A| has more entropy), under 9 bounds for
    α |A| ≤ 13;
  * a critic loss above (2 `DIVERGED` bound)², which a squared TD error reaches only with a prediction or a
    target beyond that limit (a runaway actor drives the targets' −α log π there while the critic's own
    values look sane);
  * a loss, temperature or log-probability, or any parameter of the agents, that is not finite.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

DIVERGED = 10.0


def limits(bound: float) -> tuple[float, float]:
    """(the critic's limit, the critic loss's limit) for a value bound: DIVERGED × bound and its (2 ×)²."""
    limit = DIVERGED * bound
    return limit, (2 * limit) ** 2


def diverged(train: Any, agents: Any, bound: float) -> jax.Array:
    """bool[]: whether one member's epoch diverged. `train`: its `learner.UpdateMetrics` (leaves float32[N]);
    `agents`: its `AgentState` after the epoch's updates."""
    limit, loss_limit = limits(bound)
    metrics = (train.q_loss, train.pi_loss, train.alpha, train.log_prob, train.q_max)
    finite = jnp.all(jnp.stack([jnp.isfinite(x).all() for x in metrics]))
    params = jnp.all(jnp.stack([jnp.isfinite(x).all() for x in jax.tree.leaves(agents)
                                if jnp.issubdtype(x.dtype, jnp.floating)]))
    # NaN fails every comparison: `<=` holds only for finite values within the limits.
    within = (train.q_max <= limit).all() & (train.q_loss <= loss_limit).all()
    return ~(finite & params & within)
