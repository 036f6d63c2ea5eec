"""The epoch as the trainer runs it against its earlier versions, in one process.

    python experiments/bench/epoch_versions.py                      # 3-room CSAC, one run (the speed yardstick, docs/design.md#the-learning-yardstick)
    python experiments/bench/epoch_versions.py --rooms 2 --seeds 3  # 2-room grid of 3, members one at a time

The versions, newest first; each puts one more piece back as it was:
- today's: each update gathers the next update's batch (`learner.train_loops`), so the gather
  runs beside the update instead of before it;
- "gather before each update": each update gathers its own batch first;
- "draws in the loop": each update draws its batch indices and action noise from its own key,
  where the trainer draws the whole loop's at once before it;
- "concatenated critic input": also the critic reading [obs, act] concatenated, where the trainer's
  first critic layer takes them apart (`networks.ConcatDense`, the same parameters).
All are the same grid trainer (the yardstick's settings, docs/design.md#the-learning-yardstick: "small" preset, [64, 64], the paper's epoch of
5000 env steps and 1000 joint updates, buffer 2e5, 10 evaluation episodes), the older ones built by
patching those pieces back in; their epochs alternate (order reversed every round) and the table
gives each one's median and the median of the paired ratios against today's.
"""
from __future__ import annotations

import sys
from pathlib import Path
from unittest import mock

import flax.linen as nn
import jax
import jax.numpy as jnp
import tyro

import ccp_jax.trainer as trainer_module
from ccp_jax import buffer as replay
from ccp_jax.networks import MLP, TwinCritic

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timed import Alternating, TimedGrid, alternate, emitters_on_everywhere, paired_table  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


def gather_before_each_update(learner, agents, buffer, eta, ready, key, loops, batch_size):
    """The loop with draws made before it, each update gathering its own batch first."""
    loop_keys = jax.vmap(jax.random.split)(jax.random.split(key, loops))
    idx = jax.vmap(lambda k: replay.sample_indices(buffer.size, k, batch_size))(loop_keys[:, 0])
    noise = jax.vmap(lambda k: learner.draw_noise(k, batch_size))(loop_keys[:, 1])

    def loop(agents, drawn):
        idx, noise = drawn
        return learner.update_with_noise(agents, replay.gather(buffer, idx), eta, ready, noise)
    return jax.lax.scan(loop, agents, (idx, noise))


def draws_in_the_loop(learner, agents, buffer, eta, ready, key, loops, batch_size):
    """The loop where each update draws its batch indices and noise from its own key."""
    def loop(agents, k):
        k_sample, k_update = jax.random.split(k)
        return learner.update(agents, replay.sample(buffer, k_sample, batch_size), eta, ready, k_update)
    return jax.lax.scan(loop, agents, jax.random.split(key, loops))


class ConcatenatedInput(TwinCritic):
    """The critic with one input, [obs, act] concatenated (the same parameters)."""

    @nn.compact
    def __call__(self, obs: jax.Array, act: jax.Array) -> jax.Array:
        twin = nn.vmap(MLP, variable_axes={"params": 0}, split_rngs={"params": True},
                       in_axes=None, out_axes=0, axis_size=2)
        return twin(self.hidden, 1, init_scheme=self.init_scheme)(jnp.concatenate([obs, act], -1))[..., 0]


def main(args: Alternating) -> None:
    config = args.config()
    runs = {"today's": TimedGrid(config)}
    with mock.patch.object(trainer_module, "train_loops", gather_before_each_update):
        runs["gather before each update"] = TimedGrid(config)
    with mock.patch.object(trainer_module, "train_loops", draws_in_the_loop):
        runs["draws in the loop"] = TimedGrid(config)
        with mock.patch("ccp_jax.learner.TwinCritic", ConcatenatedInput):
            runs["concatenated critic input"] = TimedGrid(config)
    alternate(runs, args.reps)
    print(f"\n{args.rooms}-room CSAC, grid of {args.seeds}, paper epoch, {args.reps} alternating epochs each\n")
    print(paired_table(runs, "today's", "today's / this", lambda today, this: today / this))


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    emitters_on_everywhere()  # before JAX computes: every version compiled as the maze epoch is
    main(tyro.cli(Alternating, description=__doc__))
