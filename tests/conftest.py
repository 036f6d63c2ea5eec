import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(__file__))  # toy_env

from ccp_jax.devices import cpu_device_flags  # noqa: E402
from envs_mjx import cpu_xla_flags  # noqa: E402

# As ccp_jax sets it, before any test imports JAX; and the CPU as one device (the CLI's default splits it
# per core), so that no test's results depend on which test first started JAX. Tests of several
# devices run in subprocesses with their own count (a later count in $XLA_FLAGS wins).
os.environ["XLA_FLAGS"] = cpu_device_flags(cpu_xla_flags(), 1)

# Many tests compile the same tiny programs; a persistent compilation cache shared by
# the session (and its subprocesses) compiles each only once.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(tempfile.gettempdir(), "ccp-jax-test-cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
# Offscreen MuJoCo rendering as envs_mjx.peg_in_hole would choose it; set before any test imports
# mujoco, so the in-process renderer and the probe in test_plot_render agree.
os.environ.setdefault("MUJOCO_GL", "egl")
