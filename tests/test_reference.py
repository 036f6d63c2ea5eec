"""ccp_jax's joint update equals an independent, plain implementation of Algorithm 2 step for step.

The reference (experiments/crosscheck/reference_csac.py) loops over agents
with one network per agent; ours stacks agents and wires critic "slots".
Both get the same noise, so after several Adam steps every parameter must
agree to float rounding.
"""
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ccp_jax.learner as learner_module
from ccp_jax.buffer import Transition
from ccp_jax.collect import completed_channels
from ccp_jax.config import Config, make_config

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments" / "crosscheck"))
import reference_csac as reference  # noqa: E402

OBS, ACT, B, HIDDEN, STEPS = 6, 2, 32, (16, 16), 4


NOISE_KEY = jax.random.PRNGKey(7)


def fixed_noise_sample(mean, log_std, key, tanh_log_prob="rlkit"):
    """The reference draws this same ε whatever its keys (RLkit's log π form); ours gets it as `fixed_noise`."""
    del key, tanh_log_prob
    return reference.gaussian_sample(mean, log_std, NOISE_KEY, "rlkit")


def fixed_noise(n_agents: int) -> "learner_module.UpdateNoise":
    """`fixed_noise_sample`'s ε for every agent and draw of our update."""
    eps = jnp.broadcast_to(jax.random.normal(NOISE_KEY, (B, ACT)), (n_agents, B, ACT))
    return learner_module.UpdateNoise(next=eps, pi=eps, successor=eps[:0])


def _batch(n_agents: int, config: Config, seed: int = 0) -> Transition:
    rng = np.random.default_rng(seed)
    f = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32)
    success = jnp.asarray(rng.uniform(size=(n_agents, B)) < 0.1, jnp.float32)
    # Agent n's s' is in stage n or (crossing) n + 1.
    next_stage = jnp.asarray(np.arange(n_agents)[:, None] + (rng.uniform(size=(n_agents, B)) < 0.3), jnp.int32)
    return Transition(obs=f(n_agents, B, OBS), action=jnp.tanh(f(n_agents, B, ACT)),
                      rewards=jnp.asarray(rng.uniform(size=(n_agents, B, n_agents)), jnp.float32),
                      next_obs=f(n_agents, B, OBS), terminal=success,
                      completed=completed_channels(config, next_stage, success), next_stage=next_stage)


def _to_reference(agents, ref: "reference.Reference") -> list[dict]:
    out = []
    for n in range(agents.log_alpha.shape[0]):
        take = lambda tree: jax.tree.map(lambda x: x[n], tree)
        twin = lambda tree: tuple({"params": jax.tree.map(lambda x: x[i], take(tree)["params"]["VmapMLP_0"])}
                                  for i in range(2))
        pi, q, la = {"params": take(agents.actor)["params"]["MLP_0"]}, twin(agents.critic), agents.log_alpha[n]
        out.append(dict(pi=pi, q=q, q_target=twin(agents.target_critic), log_alpha=la, pi_opt=ref.opt.init(pi),
                        q_opt=ref.opt.init(q), alpha_opt=ref.opt.init(la)))
    return out


@pytest.mark.parametrize("etas, absorbing_stages, ready", [
    ((0.1, 1.0), True, (True, True)),
    ((0.1, 1.0), False, (True, True)),
    ((0.3, 0.7, 1.0), True, (True, False, True)),  # a middle agent not ready yet: its critic still moves
])
def test_joint_update_equals_reference(etas, absorbing_stages, ready):
    n_agents = len(etas)
    config = make_config("paper", rooms=n_agents, hidden=HIDDEN, etas=(etas[:-1],), absorbing_stages=absorbing_stages,
                         batch_size=B, buffer_size=4 * B, tanh_log_prob="rlkit")
    nets = learner_module.make_networks(config, ACT)
    learner = learner_module.make_learner(config, nets, ACT)
    ours = learner_module.init_agents(nets, jax.random.PRNGKey(1), n_agents, OBS, ACT, value_range=20.0)

    ref = reference.Reference(reference.Settings(etas=etas, hidden=HIDDEN, absorbing_stages=absorbing_stages),
                              OBS, ACT, sample=fixed_noise_sample)
    start = theirs = _to_reference(ours, ref)
    batch, ready = _batch(n_agents, config), jnp.asarray(ready)
    per_agent = [{"obs": batch.obs[n], "action": batch.action[n], "rewards": batch.rewards[n],
                  "next_obs": batch.next_obs[n], "terminal": batch.terminal[n], "success": batch.terminal[n],
                  "next_stage": batch.next_stage[n]} for n in range(n_agents)]
    our_update, their_update = jax.jit(learner.update_with_noise), jax.jit(ref.update)
    for i in range(STEPS):
        ours, _ = our_update(ours, batch, jnp.asarray(etas, jnp.float32), ready, fixed_noise(n_agents))
        theirs = their_update(theirs, per_agent, ready, jax.random.PRNGKey(i))

    for n, (mine, other, before) in enumerate(zip(_to_reference(ours, ref), theirs, start)):
        for part in ("pi", "q", "q_target", "log_alpha"):
            moved = max(float(jnp.max(jnp.abs(a - b))) for a, b in
                        zip(jax.tree.leaves(mine[part]), jax.tree.leaves(before[part])))
            gap = max(float(jnp.max(jnp.abs(a - b))) for a, b in
                      zip(jax.tree.leaves(mine[part]), jax.tree.leaves(other[part])))
            assert gap < 1e-6, f"agent {n} {part}: differs from the reference by {gap}"
            # Every part moves, except the actor and temperature of an agent that is not ready.
            assert (moved > 0) == (bool(ready[n]) or part in ("q", "q_target")), (n, part, moved)
