"""Importing ccp_jax changes nothing global; envs_mjx.configure_cpu is the one explicit call, and MJX envs warn
once without it."""
import os
import subprocess
import sys
import warnings

import pytest

import envs_mjx

_PROBE = """
import os, sys
flags, gl = os.environ.get("XLA_FLAGS"), os.environ.get("MUJOCO_GL")
import ccp_jax, ccp_jax.train, ccp_jax.evaluate, envs_mjx, envs_mjx.maze
import jax.numpy as jnp
jnp.zeros(1).block_until_ready()  # JAX's backends start with the flags as the imports left them
hooks = [type(f).__name__ for f in sys.meta_path if type(f).__name__ == "_QuietWarpNotice"]
print("PROBE", repr((os.environ.get("XLA_FLAGS") == flags, os.environ.get("MUJOCO_GL") == gl, hooks)))
print("PROBE", repr(envs_mjx.configure_cpu()))  # too late once JAX runs, and MJX is imported: nothing changes
print("PROBE", repr((os.environ.get("XLA_FLAGS") == flags, len([f for f in sys.meta_path
                                                         if type(f).__name__ == "_QuietWarpNotice"]))))
"""


def _run(code: str, flags: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "MUJOCO_GL")}
    env.update(XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return [line.removeprefix("PROBE ") for line in done.stdout.splitlines() if line.startswith("PROBE ")]


def test_importing_the_packages_changes_no_flag_and_installs_no_hook():
    imported, late, after = _run(_PROBE, "--xla_cpu_multi_thread_eigen=true")
    assert imported == "(True, True, [])"
    assert late == "False" and after == "(True, 0)"


def test_configure_cpu_before_jax_starts_sets_the_switch_and_keeps_the_users_flags():
    code = ("import os, envs_mjx\nprint('PROBE', repr(envs_mjx.configure_cpu()))\n"
            "print('PROBE', repr(os.environ['XLA_FLAGS']))\nprint('PROBE', repr(envs_mjx.configure_cpu()))")
    first, flags, again = _run(code, "--xla_cpu_multi_thread_eigen=true")
    assert first == "True" and again == "True"
    expected = "--xla_cpu_multi_thread_eigen=true"
    if envs_mjx.emitter_switch_known():
        expected += " " + envs_mjx.XLA_CPU_FLAG
    assert flags == repr(expected)  # once, not twice


@pytest.mark.skipif(not envs_mjx.emitter_switch_known(), reason="this XLA has no fusion-emitter switch")
def test_an_unconfigured_cpu_warns_once_per_env_naming_the_call(monkeypatch):
    monkeypatch.setattr(envs_mjx, "_warned", set())
    monkeypatch.setenv("XLA_FLAGS", "")
    with pytest.warns(UserWarning, match=r"PegInHole on a CPU without envs_mjx.configure_cpu\(\).*50x"):
        assert envs_mjx.warn_if_cpu_unconfigured("PegInHole", "about 50x")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert envs_mjx.warn_if_cpu_unconfigured("PegInHole", "about 50x")  # warned already: silent
        monkeypatch.setenv("XLA_FLAGS", envs_mjx.XLA_CPU_FLAG)
        assert not envs_mjx.warn_if_cpu_unconfigured("Pusher", "14x")
