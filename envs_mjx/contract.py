"""Checks that an env meets the contract of `envs_mjx` (see its docstring; docs/design.md#environments-and-their-contract).

    from envs_mjx.contract import check_env
    check_env(MyEnv())            # raises EnvContractError listing every broken rule

The check resets a batch of `num_envs` envs with ``jax.jit(jax.vmap(env.reset))``
and steps it (by default for one whole episode) with ``jax.vmap(env.step)`` and uniform
random actions in [-1, 1], resetting envs whose episode ended (as the trainer
does). It reports each broken rule once, with where it was first seen.
"""
from __future__ import annotations

from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np

# (where in the State, dtype, shape after the batch axis; "N" and "O" stand for
# num_stages and observation_size)
_FIELDS: tuple[tuple[str, str, tuple], ...] = (
    ("obs", "float32", ("O",)),
    ("reward", "float32", ()),
    ("done", "float32", ()),
    ("info['stage']", "int32", ()),
    ("info['rewards']", "float32", ("N",)),
    ("info['truncation']", "float32", ()),
    ("info['steps']", "int32", ()),
    ("metrics['success']", "float32", ()),
)
_TOL = 1e-5
MIN_STEPS = 50  # steps checked at least, for envs with short or no stated episodes
CHUNK = 50  # steps per compiled call of the check


class EnvContractError(ValueError):
    """An env breaks the contract; `.problems` lists one message per broken rule."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("env breaks the envs_mjx contract:\n  - " + "\n  - ".join(self.problems))


def check_env(env: Any, num_envs: int = 8, steps: Optional[int] = None, seed: int = 0) -> None:
    """Raises `EnvContractError` naming every broken rule; returns None if there is none."""
    problems = violations(env, num_envs=num_envs, steps=steps, seed=seed)
    if problems:
        raise EnvContractError(problems)


def violations(env: Any, num_envs: int = 8, steps: Optional[int] = None, seed: int = 0) -> list[str]:
    """Every broken rule of the contract, one message each (empty: the env conforms).

    `steps`: how many steps the batch takes; default one whole episode (the env's `episode_length`, at least
    `MIN_STEPS`), so a fault that appears late in an episode is seen before training, not hours into it.
    """
    found = _Found()
    sizes = _sizes(env, found)
    if sizes is None:
        return found.messages()
    num_stages, obs_size, action_size = sizes
    episode_length = getattr(env, "episode_length", None)
    if steps is None:
        steps = max(MIN_STEPS, episode_length if isinstance(episode_length, (int, np.integer)) else 0)
    reset = jax.jit(jax.vmap(env.reset))
    key = jax.random.PRNGKey(seed)
    key, k_reset = jax.random.split(key)
    try:
        state = reset(jax.random.split(k_reset, num_envs))
    except Exception as err:  # any failure here is the finding
        found.add("reset fails under jit(vmap)", f"{type(err).__name__}: {_first_line(err)}")
        return found.messages()
    if not _layout(state, "reset", num_stages, obs_size, found):
        return found.messages()
    host = _host(state)
    _values(host, "reset", num_stages, found, episode_length)
    for env_i in np.flatnonzero(host["steps"] != 0)[:1]:
        found.add("info['steps'] is not 0 after reset", f"env {env_i}: {host['steps'][env_i]}")
    for env_i in np.flatnonzero(host["done"] != 0)[:1]:
        found.add("done after reset", f"env {env_i}")

    actions = jax.ShapeDtypeStruct((num_envs, action_size), jnp.float32)
    try:
        shape_after = jax.eval_shape(jax.vmap(env.step), state, actions)
    except Exception as err:
        found.add("step fails under jit(vmap)", f"{type(err).__name__}: {_first_line(err)}")
        return found.messages()
    zeros = jax.tree.map(lambda x: np.zeros(x.shape, x.dtype), shape_after)
    if not _layout(zeros, "step 1", num_stages, obs_size, found):
        return found.messages()
    # lax.scan (the trainer's collection loop) needs the carry's structure, shapes and
    # dtypes to be the same before and after a step; without, the check steps without resetting.
    same = _same_structure(jax.eval_shape(lambda s: s, state), shape_after, found)
    chunk = _chunk(env, num_envs, action_size, min(steps, CHUNK), reset=same)
    for first in range(1, steps + 1, CHUNK):
        key, k_chunk = jax.random.split(key)
        try:
            state, (before, after) = chunk(state, k_chunk)
        except Exception as err:
            found.add("step fails under jit(vmap)", f"steps {first}-{first + CHUNK - 1}: {type(err).__name__}: "
                                                    f"{_first_line(err)}")
            break
        before, after = _host(before), _host(after)
        for i in range(min(CHUNK, steps - first + 1)):
            new = {k: v[i] for k, v in before.items()}
            where = f"step {first + i}"
            _values(new, where, num_stages, found, episode_length)
            _transition(host, new, where, found)
            host = {k: v[i] for k, v in after.items()}
    return found.messages()


def _chunk(env: Any, num_envs: int, action_size: int, length: int, reset: bool):
    """A jitted function: `length` steps of the batch from `state` with uniform random actions in [-1, 1],
    resetting the envs whose episode ended (as the trainer does) when `reset`. Returns the last state and each
    step's contract fields before and after the reset (leaves [length, num_envs, ...]): one call, not one per
    step, when the env's states can be scanned."""

    def one(state: Any, key: jax.Array) -> tuple[Any, tuple[Any, Any]]:
        k_act, k_reset = jax.random.split(key)
        nxt = jax.vmap(env.step)(state, jax.random.uniform(k_act, (num_envs, action_size), jnp.float32, -1.0, 1.0))
        if not reset:
            return nxt, (_contract(nxt), _contract(nxt))
        after = _where_done(nxt.done, jax.vmap(env.reset)(jax.random.split(k_reset, num_envs)), nxt)
        return after, (_contract(nxt), _contract(after))

    if reset:
        return jax.jit(lambda state, key: jax.lax.scan(one, state, jax.random.split(key, length)))
    step = jax.jit(one)

    def unrolled(state: Any, key: jax.Array) -> tuple[Any, tuple[Any, Any]]:  # lax.scan needs equal structures
        outs = []
        for k in jax.random.split(key, length):
            state, out = step(state, k)
            outs.append(out)
        return state, jax.tree.map(lambda *x: jnp.stack(x), *outs)

    return unrolled


class _Found:
    """Broken rules in the order first seen, each with the detail of its first sighting."""

    def __init__(self):
        self._rules: dict[str, str] = {}

    def add(self, rule: str, detail: str = "") -> None:
        self._rules.setdefault(rule, detail)

    def messages(self) -> list[str]:
        return [f"{rule} ({detail})" if detail else rule for rule, detail in self._rules.items()]


def _sizes(env: Any, found: _Found) -> Optional[tuple[int, int, int]]:
    """num_stages, observation_size, action_size, each an int >= 1; None if any is not."""
    values = []
    for name in ("num_stages", "observation_size", "action_size"):
        try:
            value = getattr(env, name)
        except AttributeError:
            found.add(f"missing {name}")
            continue
        except Exception as err:
            found.add(f"{name} fails", f"{type(err).__name__}: {_first_line(err)}")
            continue
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
            found.add(f"{name} is not an int >= 1", f"got {value!r}")
            continue
        values.append(int(value))
    return tuple(values) if len(values) == 3 else None  # type: ignore[return-value]


def _get(state: Any, path: str) -> Any:
    """The leaf at `path` ("obs", "info['stage']", ...); KeyError/AttributeError if absent."""
    if "[" not in path:
        return getattr(state, path)
    field, key = path.split("[", 1)
    return getattr(state, field)[key.strip("']")]


def _layout(state: Any, where: str, num_stages: int, obs_size: int, found: _Found) -> bool:
    """Checks presence, dtype and per-env shape of every contract field; False if one is missing."""
    sizes = {"N": num_stages, "O": obs_size}
    complete = True
    for path, dtype, shape in _FIELDS:
        try:
            leaf = _get(state, path)
        except (AttributeError, KeyError, TypeError):
            found.add(f"missing {path}", where)
            complete = False
            continue
        expected = tuple(sizes.get(d, d) for d in shape)
        got = tuple(np.shape(leaf))[1:]
        if got != expected:
            long = {"N": "num_stages", "O": "observation_size"}
            names = "(" + ", ".join(long.get(d, str(d)) for d in shape) + ("," if len(shape) == 1 else "") + ")"
            expect = f"expected {names}={expected}" if shape else "expected a scalar ()"
            found.add(f"{path} has shape {got}, {expect}", where)
            complete = False
        if str(np.asarray(leaf).dtype) != dtype:
            found.add(f"{path} has dtype {np.asarray(leaf).dtype}, expected {dtype}", where)
    return complete


def _contract(state: Any) -> dict[str, jax.Array]:
    """The contract fields of a (batched) state, by their short names."""
    short = {"info['stage']": "stage", "info['rewards']": "rewards", "info['truncation']": "truncation",
             "info['steps']": "steps", "metrics['success']": "success"}
    return {short.get(path, path): _get(state, path) for path, _, _ in _FIELDS}


def _host(fields: Any) -> dict[str, np.ndarray]:
    """The contract fields of a batched state (or those `_contract` took from it) as numpy arrays."""
    return {k: np.asarray(v) for k, v in jax.device_get(fields if isinstance(fields, dict) else _contract(fields)).items()}


def _first(found: _Found, rule: str, bad: np.ndarray, where: str, show) -> None:
    """Adds `rule` if any env is `bad`, with `show(i)` of the first such env i."""
    idx = np.flatnonzero(bad)
    if idx.size:
        found.add(rule, f"{where}, env {idx[0]}: {show(idx[0])}")


def _values(s: dict[str, np.ndarray], where: str, num_stages: int, found: _Found,
            episode_length: Optional[int]) -> None:
    """Rules on one batched state."""
    r, stage, success = s["rewards"], s["stage"], s["success"]
    _first(found, "obs not finite", ~np.isfinite(s["obs"]).all(axis=-1), where, lambda i: s["obs"][i])
    _first(found, "rewards outside [0, 1]", ((r < 0) | (r > 1) | ~np.isfinite(r)).any(-1), where, lambda i: r[i])
    _first(found, "reward != sum(info['rewards'])", ~np.isclose(s["reward"], r.sum(-1), atol=_TOL * num_stages),
           where, lambda i: f"{s['reward'][i]} vs {r[i].sum()}")
    _first(found, "stage outside [0, num_stages)", (stage < 0) | (stage >= num_stages), where, lambda i: stage[i])
    for name in ("done", "truncation", "success"):
        _first(found, f"{name} not 0 or 1", (s[name] != 0) & (s[name] != 1), where, lambda i: s[name][i])
    n = np.arange(num_stages)
    clipped = np.clip(stage, 0, num_stages - 1)[:, None]
    _first(found, "rewards of completed stages != 1", ((n < clipped) & ~np.isclose(r, 1.0, atol=_TOL)).any(-1),
           where, lambda i: f"stage {stage[i]}, rewards {r[i]}")
    future = (n > clipped) & (success[:, None] == 0)  # success sets every reward to 1
    _first(found, "rewards of stages not reached != 0", (future & (r != 0)).any(-1), where,
           lambda i: f"stage {stage[i]}, rewards {r[i]}")
    _first(found, "success without all rewards 1", (success > 0) & ~np.isclose(r, 1.0, atol=_TOL).all(-1), where,
           lambda i: r[i])
    _first(found, "success without done", (success > 0) & (s["done"] == 0), where, lambda i: "")
    _first(found, "truncation without done", (s["truncation"] > 0) & (s["done"] == 0), where, lambda i: "")
    _first(found, "truncation on a success step", (s["truncation"] > 0) & (success > 0), where, lambda i: "")
    if isinstance(episode_length, (int, np.integer)):
        _first(found, "no done at episode_length steps", (s["steps"] >= episode_length) & (s["done"] == 0), where,
               lambda i: f"steps {s['steps'][i]}, episode_length {episode_length}")


def _transition(prev: dict[str, np.ndarray], new: dict[str, np.ndarray], where: str, found: _Found) -> None:
    """Rules between consecutive states of one episode (prev not done)."""
    live = prev["done"] == 0
    _first(found, "stage decreased", live & (new["stage"] < prev["stage"]), where,
           lambda i: f"{prev['stage'][i]} -> {new['stage'][i]}")
    _first(found, "info['steps'] did not count up by 1", live & (new["steps"] != prev["steps"] + 1), where,
           lambda i: f"{prev['steps'][i]} -> {new['steps'][i]}")


def _same_structure(before: Any, after: Any, found: _Found) -> bool:
    """Whether reset's and step's States have one pytree structure, shapes and dtypes."""
    leaves_b, tree_b = jax.tree_util.tree_flatten_with_path(before)
    leaves_a, tree_a = jax.tree_util.tree_flatten_with_path(after)
    if jax.tree_util.tree_structure(before) != jax.tree_util.tree_structure(after):
        keys_b = {jax.tree_util.keystr(k) for k, _ in leaves_b}
        keys_a = {jax.tree_util.keystr(k) for k, _ in leaves_a}
        diff = sorted(keys_b ^ keys_a)
        found.add("reset/step pytree structure mismatch (lax.scan needs equal structure)",
                  f"only in one of them: {', '.join(diff[:4]) or 'container types differ'}")
        return False
    for (path, b), (_, a) in zip(leaves_b, leaves_a):
        if b.shape != a.shape or b.dtype != a.dtype:
            found.add("reset/step pytree structure mismatch (lax.scan needs equal structure)",
                      f"{jax.tree_util.keystr(path)}: {b.dtype}{list(b.shape)} after reset, "
                      f"{a.dtype}{list(a.shape)} after step")
            return False
    return True


def _where_done(done: jax.Array, fresh: Any, state: Any) -> Any:
    """Per env, `fresh` where `done` else `state` (leaves [B, ...])."""
    return jax.tree.map(lambda f, s: jnp.where(done.reshape(done.shape + (1,) * (f.ndim - 1)) > 0, f, s),
                        fresh, state)


def _first_line(err: Exception) -> str:
    text = str(err).strip().splitlines()
    return text[0][:200] if text else ""
