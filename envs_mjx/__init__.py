"""Multi-stage environments for CCP, pure functions on the `brax.envs.base.Env` API.

This package knows nothing of agents. Every env here follows one contract
(the trainer relies on it; docs/design.md#environments-and-their-contract):

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

Optional, for videos: ``env.render_frames(states) -> uint8[T, H, W, 3]``, one
RGB frame per state of an episode's ``State``s stacked along a leading time
axis (host numpy leaves [T, ...]); `envs_mjx.frames` holds the built-in envs'.
"""

import contextlib
import importlib.abc
import importlib.machinery
import io
import os
import sys
import warnings

# XLA's CPU fusion emitters make MJX ~50x slower on a CPU (docs/peg.md#why-mjx-is-slow-on-a-cpu); this
# switch turns them off.
XLA_CPU_EMITTERS = "xla_cpu_use_fusion_emitters"  # the option's name, in $XLA_FLAGS and in compile options
XLA_CPU_FLAG = f"--{XLA_CPU_EMITTERS}=false"


def emitter_switch_known(jaxlib_version: str | None = None) -> bool:
    """Whether the installed XLA (``jaxlib_version``, default: the installed jaxlib's) still has the switch.

    Newer XLA dropped it and aborts on it as an unknown flag (seen with jaxlib 0.11.2 on a GPU; 0.10.2
    still has it), so it is only set where it exists.
    """
    if jaxlib_version is None:
        from importlib.metadata import PackageNotFoundError, version
        try:
            jaxlib_version = version("jaxlib")
        except PackageNotFoundError:
            return False
    major, minor = (int(part) for part in jaxlib_version.split(".")[:2])
    return (major, minor) < (0, 11)


def cpu_xla_flags(flags: str | None = None) -> str:
    """``flags`` (default: $XLA_FLAGS) with the CPU fusion-emitter switch appended if absent.

    `configure_cpu` sets it. A user's own setting of the flag is kept; an XLA without the switch gets nothing.
    """
    flags = os.environ.get("XLA_FLAGS", "") if flags is None else flags
    if XLA_CPU_EMITTERS in flags or not emitter_switch_known():
        return flags
    return (flags + " " + XLA_CPU_FLAG).strip()


def cpu_compiler_options(env) -> dict[str, bool]:
    """XLA compile options for one CPU program that steps `env`: the fusion emitters back on unless it runs MJX.

    `cpu_xla_flags` turns the emitters off process-wide, for MJX's sake only; the maze's epoch runs
    5-13 % faster with them (experiments/bench/fusion_emitters.py), so the trainer compiles its epoch
    with these options, whatever $XLA_FLAGS says. Empty for an env whose `backend` is "mjx" or unknown,
    and where XLA no longer has the switch (`emitter_switch_known`).
    """
    if getattr(env, "backend", "mjx") == "mjx" or not emitter_switch_known():
        return {}
    return {XLA_CPU_EMITTERS: True}


# mujoco.mjx.warp print()s these two lines at import whenever the optional Warp backend is absent (always,
# with our pins), which reads like an error at the top of every run; only these lines are dropped.
_WARP_MODULE = "mujoco.mjx.warp"
_WARP_NOTICES = ("Failed to import warp:", "Failed to import mujoco_warp:")


class _QuietWarpNotice(importlib.abc.MetaPathFinder):
    """Finds `mujoco.mjx.warp` as usual and runs its import with the two notices filtered out of stdout."""

    def find_spec(self, name, path, target=None):
        if name != _WARP_MODULE:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path, target)
        if spec is None or not hasattr(spec.loader, "exec_module"):
            return spec
        exec_module = spec.loader.exec_module

        def quiet_exec_module(module):
            captured = io.StringIO()
            try:
                with contextlib.redirect_stdout(captured):
                    exec_module(module)
            finally:  # anything else the import printed still reaches stdout
                sys.stdout.write("".join(line for line in captured.getvalue().splitlines(keepends=True)
                                         if not line.startswith(_WARP_NOTICES)))

        spec.loader.exec_module = quiet_exec_module
        return spec


def configure_cpu() -> bool:
    """Prepares this process to step MJX envs on a CPU; call it once, before JAX starts (before the first array).

    It switches XLA's CPU fusion emitters off in $XLA_FLAGS (`cpu_xla_flags`: with them, MJX's programs run
    about 50x slower on a CPU; a user's own setting of the switch is kept) and drops the two lines
    `mujoco.mjx` prints at import when its optional Warp backend is absent. Importing `envs_mjx` or `ccp_jax`
    changes neither: the CLI and the tools call this; a program of yours that builds a peg or pusher env on a
    CPU should too (those envs warn once when it did not). Harmless on an accelerator, where only the CPU
    flag is set and unused. Returns False, leaving $XLA_FLAGS alone, once JAX's backends are running (the
    flag is read when they start); the import filter is installed either way.
    """
    from jax._src import xla_bridge  # no public API says whether the backends have started

    if _WARP_MODULE not in sys.modules and not any(isinstance(f, _QuietWarpNotice) for f in sys.meta_path):
        sys.meta_path.insert(0, _QuietWarpNotice())
    if xla_bridge.backends_are_initialized():
        return False
    os.environ["XLA_FLAGS"] = cpu_xla_flags()
    return True


_warned: set[str] = set()


def warn_if_cpu_unconfigured(env_name: str, slowdown: str) -> bool:
    """Warns once per `env_name` when an MJX env is built on a CPU whose XLA still has the fusion emitters on.

    `slowdown` says how much slower that env runs so. Returns whether it warned (this call or an earlier one).
    """
    import jax

    if (jax.default_backend() != "cpu" or not emitter_switch_known()
            or XLA_CPU_EMITTERS in os.environ.get("XLA_FLAGS", "")):
        return False
    if env_name not in _warned:
        _warned.add(env_name)
        warnings.warn(f"{env_name} on a CPU without envs_mjx.configure_cpu() (call it before JAX starts; the "
                      f"ccp_jax CLI does): XLA's CPU fusion emitters are on, and this env runs {slowdown} slower.",
                      stacklevel=3)
    return True
