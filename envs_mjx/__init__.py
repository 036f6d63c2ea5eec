"""Multi-stage environments for CCP, pure functions on the `brax.envs.base.Env` API.

This package knows nothing of agents. Every env here follows one contract
(the trainer relies on it; SPEC §4):

* ``reset(rng) -> State`` and ``step(state, action) -> State`` are pure,
  jit- and vmap-able, with actions in ``[-1, 1]^action_size``.
* ``env.num_stages`` (int, N >= 1), ``env.observation_size``, ``env.action_size``.
* ``state.obs``: float32[observation_size], finite.
* ``state.info["stage"]``: int32 scalar, the 0-based stage U(s); never decreases
  within an episode.
* ``state.info["rewards"]``: float32[N], the subtask rewards, each in [0, 1]:
  0 for stages not reached yet, progress in [0, 1] in the current stage,
  1 for stages already completed.
* ``state.reward``: float32 scalar, ``sum(info["rewards"])``.
* ``state.metrics["success"]``: float32 scalar, 1.0 once the whole task is done.
* ``state.done``: float32, 1.0 when the episode ended, by success or by time.
* ``state.info["truncation"]``: float32, 1.0 when it ended only because the
  time limit (``episode_length`` steps, counted in ``info["steps"]``) was hit;
  truncation is not a termination and must not stop bootstrapping.
"""

import os

# XLA's CPU fusion emitters make MJX ~50x slower on CPU (PEG_NOTES.md); this switches them off.
XLA_CPU_FLAG = "--xla_cpu_use_fusion_emitters=false"


def cpu_xla_flags(flags: str | None = None) -> str:
    """``flags`` (default: $XLA_FLAGS) with the CPU fusion-emitter switch appended if absent.

    Set ``os.environ["XLA_FLAGS"] = cpu_xla_flags()`` before JAX initialises its CPU
    backend. A user's own setting of the flag is kept.
    """
    flags = os.environ.get("XLA_FLAGS", "") if flags is None else flags
    if "xla_cpu_use_fusion_emitters" in flags:
        return flags
    return (flags + " " + XLA_CPU_FLAG).strip()
