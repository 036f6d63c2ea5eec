"""Checkpoints of the whole grid's training state with orbax-checkpoint.

A checkpoint holds everything a run needs to continue bit-for-bit: parameters,
target networks, optimiser states, temperatures, replay buffers, environment
states, RNG keys and counters. Orbax writes each step to a temporary folder and
renames it when complete, so a process killed mid-write leaves the previous
checkpoint as the latest usable one.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from ccp_jax.config import ConfigError
from ccp_jax.devices import pad_grid

CHECKPOINT_DIR = "checkpoints"


class CheckpointError(ConfigError):
    """A checkpoint is missing, unreadable or does not match the run's config."""

    def __init__(self, message: str):
        super().__init__("checkpoint", message)


def manager(run_dir: Path, max_to_keep: int = 2) -> ocp.CheckpointManager:
    # Synchronous: `save` waits for the write anyway, and orbax's async manager counts that wait as the next
    # save's "Waiting for previous save" and warns about it (every save of a large replay buffer).
    return ocp.CheckpointManager(Path(run_dir).absolute() / CHECKPOINT_DIR,
                                 options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True,
                                                                      enable_async_checkpointing=False))


def _nonempty(tree: Any) -> dict[str, Any]:
    """The tree's leaves by flat index, without zero-size arrays (orbax cannot write those;
    MJX states have some, e.g. `act` of a model without actuator activations)."""
    return {str(i): x for i, x in enumerate(jax.tree.leaves(tree)) if x.size > 0}


def _rebuild(abstract: Any, saved: dict[str, Any]) -> Any:
    """Inverse of `_nonempty`: zero-size leaves come back as empty arrays of their shape and sharding."""
    leaves, treedef = jax.tree.flatten(abstract)
    return jax.tree.unflatten(treedef, [
        saved[str(i)] if str(i) in saved
        else jax.device_put(np.zeros(x.shape, x.dtype), getattr(x, "sharding", None))
        for i, x in enumerate(leaves)])


def save(mngr: ocp.CheckpointManager, epoch: int, state: Any) -> None:
    """Saves `state` as step `epoch` and waits until it is complete on disk.

    The actors' parameters are also saved as a small item of their own, so a
    policy can be loaded without reading the replay buffers.
    """
    mngr.save(epoch, args=ocp.args.Composite(state=ocp.args.StandardSave(_nonempty(state)),
                                             policy=ocp.args.StandardSave(_nonempty(state.agents.actor))))
    mngr.wait_until_finished()


def _repadded(saved: dict[str, np.ndarray], target: dict[str, Any], grid_size: int) -> dict[str, Any]:
    """Host arrays of a grid padded for other devices, cut to its `grid_size` real members and padded again
    (`pad_grid`, as `GridTrainer` pads) to the leading size of `target`'s leaves, then placed with their
    shardings."""
    return {k: jax.device_put(pad_grid(saved[k][:grid_size], want.shape[0]), getattr(want, "sharding", None))
            for k, want in target.items()}


def _unreadable(folder: Path, epoch: int, steps, err: Exception) -> CheckpointError:
    earlier = sorted(s for s in steps if s != epoch)
    hint = (f"; earlier checkpoints {earlier} are untouched: move {folder / str(epoch)} away to resume from one"
            if earlier else "")
    return CheckpointError(f"{folder / str(epoch)} cannot be restored ({type(err).__name__}: {str(err)[:300]}){hint}")


def restore(mngr: ocp.CheckpointManager, abstract_state: Any, item: str = "state",
            epoch: int | None = None, grid_size: int | None = None) -> tuple[int, Any]:
    """A complete checkpoint (default: the latest), restored into the structure and shardings
    of `abstract_state`. `item` is "state" (everything) or "policy" (the actors' parameters).

    Every leaf has the grid axis first. A checkpoint saved from another device split holds the grid padded
    to another size: given the real `grid_size`, its members are kept and the padding redone for
    `abstract_state` (in host memory), so a run resumes, or a policy loads, on any number of devices.

    Raises `CheckpointError` naming the folder when there is none, when it is
    unreadable, or when its arrays do not match the config's shapes.
    """
    steps = mngr.all_steps()
    folder = Path(mngr.directory)
    if not steps:
        raise CheckpointError(f"no complete checkpoint in {folder}")
    if epoch is None:
        epoch = max(steps)
    elif epoch not in steps:
        raise CheckpointError(f"no checkpoint of epoch {epoch} in {folder}; there are {sorted(steps)}")
    try:
        meta = ocp.StandardCheckpointHandler().metadata(folder / str(epoch) / item)
    except Exception as err:  # orbax raises many types for damaged files
        raise _unreadable(folder, epoch, steps, err) from err
    target = _nonempty(abstract_state)
    if set(meta) != set(target):
        raise CheckpointError(f"{folder / str(epoch)} holds {len(meta)} arrays where this version's {item} has "
                              f"{len(target)}: it was saved by another version of ccp-jax (or of the env); "
                              "start the run afresh")
    slots = {m.shape[0] for m in meta.values()}
    repad = grid_size is not None and slots != {x.shape[0] for x in target.values()} and min(slots) >= grid_size
    if repad and jax.process_count() > 1:
        raise CheckpointError(f"{folder / str(epoch)} holds the grid padded to {max(slots)} slots for other "
                              "devices; with several processes resume on as many devices as it was saved from")
    restore_as = {k: np.empty(m.shape, m.dtype) for k, m in meta.items()} if repad else target
    try:
        saved = mngr.restore(epoch, args=ocp.args.Composite(**{item: ocp.args.StandardRestore(restore_as)}))[item]
        state = _rebuild(abstract_state, _repadded(saved, target, grid_size) if repad else saved)
    except Exception as err:
        raise _unreadable(folder, epoch, steps, err) from err
    for got, want in zip(jax.tree.leaves(state), jax.tree.leaves(abstract_state)):
        if got.shape != want.shape or got.dtype != want.dtype:
            raise CheckpointError(f"{folder / str(epoch)} holds an array {got.shape} {got.dtype} where "
                                  f"the config expects {want.shape} {want.dtype}")
    return epoch, state
