"""Population-based training (PBT) of the cooperative ratio η inside the compiled grid (docs/pbt.md).

With `pbt_every` K > 0 each member carries its ratios in its state (`PbtMember`) instead of receiving them
from the grid's constant ratios, and sums its training episodes' outcomes since the last ranking. Every K
epochs, at the end of the epoch and inside the same compiled program (`exploit_explore`):

- fitness (`fitness`): of the training episodes that ended since the last ranking, the mean fraction of the
  task's N stages each completed (a success counts N of N): success and progress towards it in one number;
- exploit (`select`, truncation selection): each of the bottom ⌊pbt_fraction × G⌋ (at least one) members
  copies the whole state (networks, optimiser states, temperatures, normaliser bounds, buffers, env states,
  counters) of a member drawn at random from the top as many, where that one is strictly fitter;
- explore (`perturb`): a copy's ratio of each cooperative agent is, independently, redrawn uniformly in
  [0, 1] with probability `pbt_resample`, else multiplied by one of `pbt_factors`; clipped to [0, 1];
- a copy's key is the donor's with its own member index folded in, so the two go on with different samples.

The copy is a gather and scatter of the replaced rows along the grid axis (`copy_members`), so a grid
sharded over devices needs no other code: XLA moves the donors' rows between devices. Padded members (copies
that fill the last device) are never ranked, never copied and never replaced.
docs/design.md#population-based-training-of-the-ratio says why.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple, TypeVar

import jax
import jax.numpy as jnp
from flax import struct

from ccp_jax.collect import EpisodeStats
from ccp_jax.config import Config

if TYPE_CHECKING:
    from ccp_jax.trainer import TrainState  # trainer.py imports this module

Tree = TypeVar("Tree")

STREAM = 0x9B7  # folded into a member's key for its PBT draws, so they never reuse a training draw


class PbtMember(struct.PyTreeNode):
    """One member's PBT state (the grid adds a leading axis)."""

    eta: jax.Array  # float32[N]: the ratios it trains with; the last agent's stays 1
    window: EpisodeStats  # its training episodes since the last ranking, summed


class PbtRecord(NamedTuple):
    """What an epoch's PBT step did, per member (the grid adds a leading axis)."""

    eta: jax.Array  # float32[N]: the ratios after the step, those the next epoch trains with
    parent: jax.Array  # int32[]: the member it copied, -1 where it copied none
    fitness: jax.Array  # float32[]: the fitness of its window this epoch (`fitness`); the ranking's at a ranking


def init_member(eta: jax.Array) -> PbtMember:
    """A member's PBT state before its first epoch: eta float32[N], the grid's ratios for it (no "auto")."""
    n = eta.shape[-1]
    zero = jnp.zeros((), jnp.float32)
    return PbtMember(eta=jnp.asarray(eta, jnp.float32),
                     window=EpisodeStats(episodes=zero, successes=zero, stages=jnp.zeros((n,), jnp.float32)))


def accumulate(member: PbtMember, stats: EpisodeStats) -> PbtMember:
    """`member` with an epoch's training-episode counts `stats` added to its window."""
    return member.replace(window=jax.tree.map(jnp.add, member.window, stats))


def fitness(window: EpisodeStats) -> jax.Array:
    """The mean fraction of the N stages completed by the window's ended episodes, float32[...] in [0, 1].

    window leaves [..., ] / stages [..., N] (`EpisodeStats`, stages[n] = episodes that reached stage n, so
    stages[0] counts them all): an episode that reached stage n but failed completed n of N; a success N of N.
    0 where no episode ended.
    """
    n = window.stages.shape[-1]
    completed = window.stages[..., 1:].sum(-1) + window.successes
    return completed / (n * jnp.maximum(window.episodes, 1.0))


def replaced_count(grid_size: int, fraction: float) -> int:
    """How many members a ranking replaces (and how many it copies from): ⌊fraction × G⌋, at least 1."""
    return max(1, int(fraction * grid_size))


def select(fit: jax.Array, keys: jax.Array, fraction: float,
           grid_size: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Truncation selection: (source int32[P], copied bool[P], bottom int32[C]) for fit float32[P] and one key
    per member [P, 2], C = `replaced_count`.

    The first `grid_size` of the P members are ranked (the rest are padding: always their own source). Each
    of the `bottom` C draws a donor from the top C with its own key and copies it where the donor's fitness
    is strictly higher (so an unranked population, all at 0, keeps its diversity). Ties in rank go to the
    lower member index.
    """
    padded = fit.shape[0]
    count = replaced_count(grid_size, fraction)
    order = jnp.argsort(-fit[:grid_size], stable=True)  # best first
    rank = jnp.zeros((grid_size,), jnp.int32).at[order].set(jnp.arange(grid_size, dtype=jnp.int32))
    rank = jnp.concatenate([rank, jnp.full((padded - grid_size,), -1, jnp.int32)])  # padding: never bottom
    picks = jax.vmap(lambda k: jax.random.randint(k, (), 0, count))(keys)
    donor = order[picks].astype(jnp.int32)
    copied = (rank >= grid_size - count) & (fit[donor] > fit)
    return jnp.where(copied, donor, jnp.arange(padded, dtype=jnp.int32)), copied, order[grid_size - count:]


def perturb(eta: jax.Array, keys: jax.Array, config: Config) -> jax.Array:
    """Every member's ratios explored, eta float32[P, N] -> float32[P, N], one key per member [P, 2].

    Each cooperative agent's ratio independently: with probability `pbt_resample` drawn uniformly in [0, 1],
    else multiplied by one of `pbt_factors` (even odds); clipped to [0, 1]. The last agent's stays as it is.
    """
    low, high = config.ccp.pbt_factors

    def one(e, key):
        k_resample, k_uniform, k_factor = jax.random.split(key, 3)
        shape = e.shape
        factor = jnp.where(jax.random.bernoulli(k_factor, 0.5, shape), high, low)
        moved = jnp.where(jax.random.uniform(k_resample, shape) < config.ccp.pbt_resample,
                          jax.random.uniform(k_uniform, shape), e * factor)
        cooperative = jnp.arange(shape[0]) < shape[0] - 1
        return jnp.where(cooperative, jnp.clip(moved, 0.0, 1.0), e).astype(e.dtype)

    return jax.vmap(one)(eta, keys)


def copy_members(tree: Tree, rows: jax.Array, source: jax.Array) -> Tree:
    """Every leaf's `rows` int32[C] along the grid axis replaced by its rows `source` int32[C]: a gather and a
    scatter of C rows, sharded or not (only the rows that may change are gathered, not the whole grid)."""
    return jax.tree.map(lambda x: x.at[rows].set(x[source]), tree)


def exploit_explore(state: TrainState, config: Config, grid_size: int) -> tuple[TrainState, PbtRecord]:
    """One PBT ranking of a grid's state (leaves [P, ...]; `.key` [P, 2], `.pbt` a `PbtMember`).

    Returns (state, `PbtRecord` [P]): copied members hold their donor's whole state with their own member
    index folded into its key and their ratios perturbed (`perturb`); every member's window starts anew.
    """
    padded = state.key.shape[0]
    members = jnp.arange(padded, dtype=jnp.uint32)
    fit = fitness(state.pbt.window)
    draws = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, STREAM)))(state.key)  # [P, 2, 2]
    source, copied, bottom = select(fit, draws[:, 0], config.ccp.pbt_fraction, grid_size)
    new = copy_members(state, bottom, source[bottom])
    key = jnp.where(copied[:, None], jax.vmap(jax.random.fold_in)(new.key, members), new.key)
    eta = jnp.where(copied[:, None], perturb(new.pbt.eta, draws[:, 1], config), new.pbt.eta)
    window = jax.tree.map(jnp.zeros_like, new.pbt.window)
    new = new.replace(key=key, pbt=PbtMember(eta=eta, window=window))
    return new, PbtRecord(eta=eta, parent=jnp.where(copied, source, -1), fitness=fit)


def pbt_step(state: TrainState, config: Config, grid_size: int) -> tuple[TrainState, PbtRecord]:
    """After every member's epoch: `exploit_explore` where the epoch count is a multiple of `pbt_every`, else
    the state as it is. Returns (state, `PbtRecord` [P])."""
    padded = state.key.shape[0]
    unchanged = lambda s: (s, PbtRecord(eta=s.pbt.eta, parent=jnp.full((padded,), -1, jnp.int32),
                                        fitness=fitness(s.pbt.window)))
    ranking = state.epoch[0] % config.ccp.pbt_every == 0
    return jax.lax.cond(ranking, lambda s: exploit_explore(s, config, grid_size), unchanged, state)
