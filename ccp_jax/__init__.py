"""ccp-jax: Cooperative Consecutive Policies (CSAC) for multi-stage RL, end to end in JAX.

The public API is imported lazily, so `python -m ccp_jax.plot` and friends start
without loading JAX, brax and MuJoCo first.
"""
import importlib
import os

from envs_mjx import cpu_xla_flags

# Before JAX starts: the CPU fusion emitters slow MJX ~50x (a user's own setting is kept).
os.environ["XLA_FLAGS"] = cpu_xla_flags()

_EXPORTS = {
    "Config": "ccp_jax.config", "ConfigError": "ccp_jax.config", "make_config": "ccp_jax.config",
    "load_policy": "ccp_jax.policy", "evaluate_run": "ccp_jax.evaluate", "run": "ccp_jax.train",
}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'ccp_jax' has no attribute {name!r}")
