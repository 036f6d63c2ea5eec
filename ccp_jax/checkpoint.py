"""Checkpoints of the whole grid's training state with orbax-checkpoint.

A checkpoint holds everything a run needs to continue bit-for-bit: parameters,
target networks, optimiser states, temperatures, replay buffers, environment
states, RNG keys and counters. Orbax writes each step to a temporary folder and
renames it when complete, so a process killed mid-write leaves the previous
checkpoint as the latest usable one.
"""
from __future__ import annotations

import errno
import sys
import warnings
from pathlib import Path
from typing import Any, Callable

import jax
import numpy as np
import orbax.checkpoint as ocp

from ccp_jax.config import ConfigError
from ccp_jax.devices import pad_grid

CHECKPOINT_DIR = "checkpoints"

# Leaves that a fixed bug saved in another shape; given defaults they restart from their initial value, with a
# warning, instead of refusing the checkpoint. SAC's gate of the outcome rules (one agent: never read) was saved
# with one entry per stage.
RESET_IF_RESHAPED = {("successor_succeeded",)}


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


def _name(key: Any) -> str:
    """One step of a pytree path as a checkpoint key: a field or dict key by name, a sequence index as #i."""
    if isinstance(key, jax.tree_util.GetAttrKey):
        return key.name
    if isinstance(key, jax.tree_util.DictKey):
        return str(key.key)
    return f"#{getattr(key, 'idx', getattr(key, 'key', key))}"


def leaf_names(tree: Any) -> list[tuple[str, ...]]:
    """Every leaf's path in `tree` as names (`_name`), in the order of `jax.tree.leaves`."""
    return [tuple(_name(k) for k in path) for path, _ in jax.tree_util.tree_flatten_with_path(tree)[0]]


def _flat(nested: dict[str, Any], prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    """{path: leaf} of a nested dict (a checkpoint's tree or its metadata)."""
    out = {}
    for name, value in nested.items():
        if isinstance(value, dict):
            out.update(_flat(value, prefix + (name,)))
        else:
            out[prefix + (name,)] = value
    return out


def _nest(flat: dict[tuple[str, ...], Any]) -> dict[str, Any]:
    """Inverse of `_flat`."""
    nested: dict[str, Any] = {}
    for names, x in flat.items():
        node = nested
        for name in names[:-1]:
            node = node.setdefault(name, {})
        node[names[-1]] = x
    return nested


def _keyed(tree: Any) -> dict[str, Any]:
    """The tree's leaves as a nested dict keyed by their paths' names, so a checkpoint stays readable when a field
    is added to the state; zero-size arrays are left out (orbax cannot write those; MJX states have some)."""
    return _nest({names: x for names, x in zip(leaf_names(tree), jax.tree.leaves(tree)) if x.size > 0})


def save(mngr: ocp.CheckpointManager, epoch: int, state: Any) -> None:
    """Saves `state` as step `epoch` and waits until it is complete on disk.

    The actors' parameters are also saved as a small item of their own, so a
    policy can be loaded without reading the replay buffers.
    """
    try:
        mngr.save(epoch, args=ocp.args.Composite(state=ocp.args.StandardSave(_keyed(state)),
                                                 policy=ocp.args.StandardSave(_keyed(state.agents.actor))))
        mngr.wait_until_finished()
    except Exception as err:  # TensorStore reports a full disk as a ValueError; say it as the OS would
        if isinstance(err, OSError) or "RESOURCE_EXHAUSTED" not in str(err):
            raise
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(mngr.directory) / str(epoch))) from err


def _repadded(saved: np.ndarray, want: Any, grid_size: int) -> Any:
    """A host array of a grid padded for other devices, cut to its `grid_size` real members and padded again
    (`pad_grid`, as `GridTrainer` pads) to the leading size of `want`, then placed with its sharding."""
    return jax.device_put(pad_grid(saved[:grid_size], want.shape[0]), getattr(want, "sharding", None))


def _drop_abandoned_reads() -> None:
    """When one array of a checkpoint fails to read, orbax abandons its other reads (coroutines), and each prints
    a page of traceback whenever it is collected, even before the failure reaches us. Installed before the first
    read: those reports alone are dropped; every other unraisable exception still reaches the previous hook."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_abandoned_reads", False):
        return

    def hook(unraisable: Any) -> None:
        if getattr(getattr(unraisable.object, "cr_code", None), "co_name", "") != ABANDONED_READ:
            previous(unraisable)

    hook.drops_abandoned_reads = True
    sys.unraisablehook = hook


ABANDONED_READ = "_read_array_index_and_device_put"  # orbax's coroutine that reads one array


class UnreadableCheckpoint(CheckpointError):
    """A checkpoint's files cannot be read (damaged, cut short); an older checkpoint may still be whole."""


def _unreadable(folder: Path, epoch: int, steps, err: Exception) -> CheckpointError:
    earlier = sorted(s for s in steps if s != epoch)
    hint = (f"; earlier checkpoints {earlier} are untouched: move {folder / str(epoch)} away to resume from one"
            if earlier else "")
    cause = (str(err).strip().splitlines() or [""])[0][:200]  # the first line: TensorStore appends pages of spec
    return UnreadableCheckpoint(f"{folder / str(epoch)} cannot be restored ({type(err).__name__}: {cause}){hint}")


def _match(saved: dict[tuple[str, ...], Any], abstract_state: Any, item: str, where: Path, defaults: Any) -> list:
    """Per leaf of `abstract_state` (in leaf order): the checkpoint path it restores from, "empty" (a zero-size
    leaf) or "default" (a leaf the checkpoint lacks, taken from `defaults`). Checkpoints written before leaves
    were keyed by path are matched by position, and only if they hold as many arrays as the state.
    `saved`: the checkpoint's arrays (metadata) by path (`_flat`)."""
    leaves = jax.tree.leaves(abstract_state)
    if all(len(k) == 1 and k[0].isdigit() for k in saved):  # keyed by position
        nonempty = sum(x.size > 0 for x in leaves)
        if len(saved) != nonempty:
            raise CheckpointError(f"{where} holds {len(saved)} arrays where this version's {item} has {nonempty}: it "
                                  "was saved by another version of ccp-jax (or of the env); start the run afresh")
        return ["empty" if x.size == 0 else (str(i),) for i, x in enumerate(leaves)]
    keys = [names if x.size > 0 else "empty" for names, x in zip(leaf_names(abstract_state), leaves)]
    missing = ["/".join(k) for k in keys if k != "empty" and k not in saved]
    if missing and defaults is None:
        raise CheckpointError(f"{where} lacks {len(missing)} of this version's {item} arrays ({', '.join(missing[:4])}"
                              f"{' ...' if len(missing) > 4 else ''}): it was saved by another version of ccp-jax; "
                              "start the run afresh")
    for i, (k, x) in enumerate(zip(keys, leaves)):
        if k in saved and (saved[k].shape[1:] != x.shape[1:] or np.dtype(saved[k].dtype) != np.dtype(x.dtype)):
            if k in RESET_IF_RESHAPED and defaults is not None:
                warnings.warn(f"{where}: array {'/'.join(k)} was saved as {saved[k].shape} where this version "
                              f"keeps {x.shape}; it starts from its initial value", stacklevel=3)
                keys[i] = "default"
                continue
            raise CheckpointError(f"{where}: array {'/'.join(k)} is {saved[k].shape} {saved[k].dtype} where this "
                                  f"version expects {x.shape} {x.dtype}; start the run afresh")
    if missing:
        warnings.warn(f"{where}: {len(missing)} arrays this version's {item} adds are not in the checkpoint and "
                      f"start from their initial values: {', '.join(missing)}", stacklevel=3)
    return [k if k == "empty" or k in saved else "default" for k in keys]


def restore(mngr: ocp.CheckpointManager, abstract_state: Any, item: str = "state", epoch: int | None = None,
            grid_size: int | None = None, defaults: Any | Callable[[], Any] = None) -> tuple[int, Any]:
    """A complete checkpoint (default: the latest), restored into the structure and shardings
    of `abstract_state`. `item` is "state" (everything) or "policy" (the actors' parameters).

    Leaves are found by their path in the state, so a checkpoint written before a field was added still
    restores: given `defaults` (a state of the same structure, e.g. the trainer's init, or a function returning
    one, called only when a leaf is missing), the added leaves take its values and a warning names them;
    without, the checkpoint is refused naming them. A leaf whose shape
    or dtype changed is refused by name. Every leaf has the grid axis first. A checkpoint saved from another
    device split holds the grid padded to another size: given the real `grid_size`, its members are kept and
    the padding redone for `abstract_state` (in host memory), so a run resumes, or a policy loads, on any
    number of devices.

    Raises `CheckpointError` naming the folder when there is none, when it is unreadable, or when its
    arrays do not match the config's.
    """
    steps = mngr.all_steps()
    folder = Path(mngr.directory)
    if not steps:
        raise CheckpointError(f"no complete checkpoint in {folder}: a run stopped before its first checkpoint "
                              "cannot be resumed; start it again with another --out (or delete that folder)")
    if epoch is None:
        epoch = max(steps)
    elif epoch not in steps:
        raise CheckpointError(f"no checkpoint of epoch {epoch} in {folder}; there are {sorted(steps)}")
    try:
        meta = ocp.StandardCheckpointHandler().metadata(folder / str(epoch) / item)
    except Exception as err:  # orbax raises many types for damaged files
        raise _unreadable(folder, epoch, steps, err) from err
    leaves, treedef = jax.tree.flatten(abstract_state)
    flat_meta = _flat(meta)
    sources = _match(flat_meta, abstract_state, item, folder / str(epoch), defaults)
    wanted = {k: x for k, x in zip(sources, leaves) if k not in ("empty", "default")}
    slots = {m.shape[0] for m in flat_meta.values()}
    repad = grid_size is not None and slots != {x.shape[0] for x in wanted.values()} and min(slots) >= grid_size
    if repad and jax.process_count() > 1:
        raise CheckpointError(f"{folder / str(epoch)} holds the grid padded to {max(slots)} slots for other "
                              "devices; with several processes resume on as many devices as it was saved from")
    # Every saved array is read (orbax restores whole trees); those this state no longer has are dropped.
    restore_as = {k: (np.empty(m.shape, m.dtype) if repad or k not in wanted else wanted[k])
                  for k, m in flat_meta.items()}
    _drop_abandoned_reads()
    try:
        saved = _flat(mngr.restore(epoch, args=ocp.args.Composite(
            **{item: ocp.args.StandardRestore(_nest(restore_as))}))[item])
    except Exception as err:
        raise _unreadable(folder, epoch, steps, err) from err
    if "default" in sources and callable(defaults):
        defaults = defaults()
    default_leaves = jax.tree.leaves(defaults) if "default" in sources else [None] * len(leaves)
    state = jax.tree.unflatten(treedef, [
        jax.device_put(np.zeros(x.shape, x.dtype), getattr(x, "sharding", None)) if k == "empty"
        else d if k == "default" else _repadded(saved[k], x, grid_size) if repad else saved[k]
        for k, x, d in zip(sources, leaves, default_leaves)])
    for got, want in zip(jax.tree.leaves(state), leaves):
        if got.shape != want.shape or got.dtype != want.dtype:
            raise CheckpointError(f"{folder / str(epoch)} holds an array {got.shape} {got.dtype} where "
                                  f"the config expects {want.shape} {want.dtype}")
    return epoch, state

