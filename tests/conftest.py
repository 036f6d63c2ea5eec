import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))  # toy_env

from envs_mjx import cpu_xla_flags  # noqa: E402

os.environ["XLA_FLAGS"] = cpu_xla_flags()  # as ccp_jax sets it, before any test imports JAX

# Many tests compile the same tiny programs; a persistent compilation cache shared by
# the session (and its subprocesses) compiles each only once.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(tempfile.gettempdir(), "ccp-jax-test-cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
# Offscreen MuJoCo rendering as envs_mjx.peg_in_hole would choose it; set before any test imports
# mujoco, so the in-process renderer and the probe in test_plot_render agree.
os.environ.setdefault("MUJOCO_GL", "egl")
