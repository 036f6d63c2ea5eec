"""C MuJoCo behind `jax.pure_callback`: the peg env's physics with ``physics="c"`` (docs/peg.md#c-physics).

On a CPU an MJX physics step is a chain of many small XLA operations, each costing far more than its
arithmetic; C MuJoCo's ``mj_step`` on the same model is 10-15x faster per control step even behind a host
callback (docs/peg.md#where-a-control-step-goes). This module steps the peg models in C and hands JAX two
things per environment:

* the complete physics state, ``mjSTATE_INTEGRATION`` (time, qpos, qvel, act, qacc_warmstart, ctrl, applied
  forces, eq_active: everything ``mj_step`` reads besides the model), float64 bit-cast to uint32 pairs, so a
  JAX array carries it losslessly and the env stays a pure function of its state: the C simulation inside
  the env is C MuJoCo's own trajectory, bit for bit, however the batch is split, vmapped or resumed;
* a float32 readout of what the env's controller, observation, rewards and grasp check read, laid out by
  `readout_layout` (`CPhysics.unpack` turns the flat vector into named arrays).

One host call per control step serves the whole batch (``vmap_method="broadcast_all"``: any number of
nested vmaps arrive as leading axes, flattened here). Each call takes a pool of ``MjData`` (one per batch
row) from a free list and returns it afterwards; a row's data is entirely overwritten from the carried
state before it is stepped, so which data serves which row never shows in the results. Under
``shard_map`` each device calls with its shard, possibly at the same time, hence one pool per call.

The callback is a pure function of its inputs, which is what `jax.pure_callback` asks: XLA may drop a call
whose results are unused or merge identical calls, and either leaves the results unchanged.
"""
from __future__ import annotations

import contextlib
import threading
from typing import Iterator, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

STATE_SPEC = mujoco.mjtState.mjSTATE_INTEGRATION
TOUCH_DIST = 5e-4  # a pad touches the peg: penetrating or less than 0.5 mm apart (the MJX env's contact test)
# C MuJoCo resets the data (and warns) instead of producing NaN; these warnings mark such a step.
_BAD = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQACC)


def readout_layout(nq: int, nv: int, jac_cols: int) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """(name, shape) of each readout field, in the order of the flat float32 vector.

    qpos [nq], qvel [nv]; grip site position [3] and rotation matrix [3, 3]; peg body position [3]; hand body
    quaternion [4]; peg tip site position [3]; left/right pad touches the peg [2] (1.0 / 0.0); the grip site's
    Jacobian [6, jac_cols] (translation rows, then rotation) w.r.t. the robot's dofs, left out if jac_cols is 0.
    """
    fields = [("qpos", (nq,)), ("qvel", (nv,)), ("grip_pos", (3,)), ("grip_mat", (3, 3)), ("peg_pos", (3,)),
              ("hand_quat", (4,)), ("tip_pos", (3,)), ("touch", (2,))]
    if jac_cols:
        fields.append(("jac", (6, jac_cols)))
    return tuple(fields)


class CPhysics:
    """The peg model stepped in C MuJoCo, callable from jitted, vmapped JAX (`step`, `reset`).

    ``jac_dofs``: the robot's dofs whose grip-site Jacobian the readout carries (the arm's 7; empty for the
    hand, whose controller needs none).
    """

    def __init__(self, m: mujoco.MjModel, n_substeps: int, grip_site: int, tip_site: int, peg_body: int,
                 hand_body: int, pads: Sequence[int], peg_geoms: Sequence[int], jac_dofs: Sequence[int]):
        self.m, self.n_substeps = m, int(n_substeps)
        self.grip_site, self.tip_site, self.peg_body, self.hand_body = grip_site, tip_site, peg_body, hand_body
        self.pads, self.peg_geoms = tuple(int(p) for p in pads), tuple(int(g) for g in peg_geoms)
        self.jac_dofs = np.asarray(jac_dofs, int)
        self.state_size = mujoco.mj_stateSize(m, STATE_SPEC)  # float64 values; 2x as many uint32 words
        self.layout = readout_layout(m.nq, m.nv, len(self.jac_dofs))
        self.readout_size = sum(int(np.prod(s)) for _, s in self.layout)
        # Pools of MjData (one per batch row) not in use; concurrent calls (several devices) each take their own.
        # Not threading.local: XLA runs callbacks on its own threads, whose Python thread state (and with it
        # any thread-local pool) lives for one call only; destroying the pool there crashed the process.
        self._free: list[list] = []
        self._lock = threading.Lock()

    # ----- JAX side ------------------------------------------------------------------------------
    def step(self, bits: jax.Array, ctrl: jax.Array) -> tuple[jax.Array, jax.Array]:
        """``n_substeps`` physics steps under ``ctrl`` float32[nu] from state ``bits`` uint32[2S]:
        (the new state uint32[2S], its readout float32[R]). Any leading (vmapped) axes pass through."""
        out = (jax.ShapeDtypeStruct(bits.shape, jnp.uint32), jax.ShapeDtypeStruct((self.readout_size,), jnp.float32))
        return jax.pure_callback(self._host_step, out, bits, ctrl, vmap_method="broadcast_all")

    def reset(self, qpos: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The state at ``qpos`` float32[nq] with zero velocity, control and warm start, after C's forward pass
        (``mj_forward``): (state uint32[2S], readout float32[R])."""
        out = (jax.ShapeDtypeStruct((2 * self.state_size,), jnp.uint32),
               jax.ShapeDtypeStruct((self.readout_size,), jnp.float32))
        return jax.pure_callback(self._host_reset, out, qpos, vmap_method="broadcast_all")

    def unpack(self, flat: jax.Array) -> dict[str, jax.Array]:
        """The readout float32[R] as named arrays (`readout_layout`): "touch" as bool[2], "jac" None if left out."""
        out, i = {}, 0
        for name, shape in self.layout:
            n = int(np.prod(shape))
            out[name] = flat[i:i + n].reshape(shape)
            i += n
        out["touch"] = out["touch"] > 0.5
        out.setdefault("jac", None)
        return out

    def state_qpos(self, bits: np.ndarray) -> np.ndarray:
        """The exact float64 qpos [..., nq] of host state bits uint32[..., 2S] (rendering, tests)."""
        full = np.ascontiguousarray(bits, np.uint32).view(np.float64)
        return full[..., 1:1 + self.m.nq]  # mjSTATE_INTEGRATION starts with time, then qpos

    # ----- host side ------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _datas(self, n: int) -> Iterator[list]:
        """A pool of at least ``n`` MjData for this call alone, returned to the free list afterwards."""
        with self._lock:
            pool = self._free.pop() if self._free else []
        while len(pool) < n:
            pool.append(mujoco.MjData(self.m))
        try:
            yield pool
        finally:
            with self._lock:
                self._free.append(pool)

    def _host_step(self, bits: np.ndarray, ctrl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lead = bits.shape[:-1]
        states = np.ascontiguousarray(bits, np.uint32).reshape(-1, bits.shape[-1]).view(np.float64)
        ctrls = np.asarray(ctrl, np.float64).reshape(-1, ctrl.shape[-1])
        new, ro = np.empty_like(states), np.empty((len(states), self.readout_size), np.float32)
        with self._datas(len(states)) as pool:
            for i, d in zip(range(len(states)), pool):
                self._step_one(d, states[i], ctrls[i], new[i], ro[i])
        return new.view(np.uint32).reshape(lead + (bits.shape[-1],)), ro.reshape(lead + (self.readout_size,))

    def _host_reset(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lead = qpos.shape[:-1]
        qs = np.asarray(qpos, np.float64).reshape(-1, qpos.shape[-1])
        new = np.empty((len(qs), self.state_size), np.float64)
        ro = np.empty((len(qs), self.readout_size), np.float32)
        m = self.m
        with self._datas(len(qs)) as pool:
            for i, d in zip(range(len(qs)), pool):
                mujoco.mj_resetData(m, d)
                d.qpos[:] = qs[i]
                mujoco.mj_forward(m, d)
                mujoco.mj_getState(m, d, new[i], STATE_SPEC)
                self._read(d, ro[i])
        return new.view(np.uint32).reshape(lead + (2 * self.state_size,)), ro.reshape(lead + (self.readout_size,))

    def _step_one(self, d: mujoco.MjData, state: np.ndarray, ctrl: np.ndarray, new: np.ndarray,
                  ro: np.ndarray) -> None:
        """One row: ``d`` set to ``state`` float64[S] and ``ctrl``, stepped; the new state and readout written."""
        m = self.m
        mujoco.mj_setState(m, d, state, STATE_SPEC)
        d.ctrl[:] = ctrl
        for w in _BAD:
            d.warning[w].number = 0
        mujoco.mj_step(m, d, nstep=self.n_substeps)
        if any(d.warning[w].number for w in _BAD):  # C reset the data; the MJX env would hold NaN
            new[:], ro[:] = np.nan, np.nan
            return
        mujoco.mj_getState(m, d, new, STATE_SPEC)
        self._read(d, ro)

    def _read(self, d: mujoco.MjData, out: np.ndarray) -> None:
        """Fill one readout row (`readout_layout`) from ``d`` as ``mj_step`` left it: positions, rotations,
        contacts and Jacobian are those of the last substep's forward pass, as in an ``mjx.step``'s data."""
        m, nv = self.m, self.m.nv
        i = 0
        for value in (d.qpos, d.qvel, d.site_xpos[self.grip_site], d.site_xmat[self.grip_site],
                      d.xpos[self.peg_body], d.xquat[self.hand_body], d.site_xpos[self.tip_site]):
            n = value.size
            out[i:i + n] = value.ravel()
            i += n
        for pad in self.pads:
            dist = min(mujoco.mj_geomDistance(m, d, pad, g, TOUCH_DIST, None) for g in self.peg_geoms)
            out[i] = 1.0 if dist < TOUCH_DIST else 0.0
            i += 1
        if len(self.jac_dofs):
            jacp, jacr = np.empty((3, nv)), np.empty((3, nv))
            mujoco.mj_jacSite(m, d, jacp, jacr, self.grip_site)
            out[i:] = np.concatenate([jacp[:, self.jac_dofs], jacr[:, self.jac_dofs]]).ravel()
