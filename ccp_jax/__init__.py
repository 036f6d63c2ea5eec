"""ccp-jax: Cooperative Consecutive Policies (CSAC) for multi-stage RL, end to end in JAX."""
from ccp_jax.config import Config, ConfigError, make_config
from ccp_jax.policy import load_policy
from ccp_jax.train import run

__all__ = ["Config", "ConfigError", "make_config", "load_policy", "run"]
