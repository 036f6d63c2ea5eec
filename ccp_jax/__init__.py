"""ccp-jax: Cooperative Consecutive Policies (CSAC) for multi-stage RL, end to end in JAX.

The public API is imported lazily, so `python -m ccp_jax.plot` and friends start
without loading JAX, brax and MuJoCo first. Importing this package changes
nothing global: a program that steps MJX envs (peg, pusher) on a CPU calls
`ccp_jax.configure_cpu()` (= `envs_mjx.configure_cpu`) once before JAX starts,
as the CLI and the tools do.
"""
import importlib

_EXPORTS = {
    "Config": "ccp_jax.config", "ConfigError": "ccp_jax.config", "make_config": "ccp_jax.config",
    "load_policy": "ccp_jax.policy", "evaluate_run": "ccp_jax.evaluate", "run": "ccp_jax.train",
    "configure_cpu": "envs_mjx",
}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'ccp_jax' has no attribute {name!r}")
