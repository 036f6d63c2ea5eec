"""Peg in hole with a Panda arm on MuJoCo MJX: grasp, then insert (two stages).

The paper's second domain (docs/peg.md), as a pure-functional ``brax.envs.base.Env``.
Two robot models do the same task (``model``): "arm", the Panda arm with the Franka
Hand described below (``assets/panda_peg.xml``), and "hand", the Franka Hand alone on
a slide along x with a velocity servo (``assets/hand_peg.xml``): y, z and orientation
are held by construction instead of by the arm's controller, and the scene, peg,
fingers, contacts, actions, observation layout, rewards, stages and resets are the
arm's. On a CPU the hand steps 1.6x (one env) to 2.5x (16) faster (docs/peg.md#the-hand-variant).
Two physics step either model (``physics``): "mjx", MuJoCo MJX inside the compiled program (any JAX device),
and "c", C MuJoCo on the host behind ``jax.pure_callback`` (`envs_mjx.peg_c`; docs/peg.md#c-physics). The
env's controller, observation, rewards and grasp check read one `Readout` that either physics fills.

Scene (``assets/panda_peg.xml``; all numbers in metres, world frame, x from the robot
towards the block): a block whose front face is at x = 0.60 has a 20 mm square
through-hole along x with its axis at (y, z) = (0, 0.02). A peg lies on the table
in front of it, pointing at the hole: a thick section (box, 0.06 long, 40 mm square)
at the back and a thin section (capsule, radius 8 mm, 0.10 long) at the front; lying
on its box, the peg's axis is the hole's axis. The peg's centre (the midpoint of its
0.16 m length, its frame origin) lies 0.02 m into the thin section.

Why one velocity axis is enough (the paper's "end-effector velocity along the axis of
actuation"): the hand points down with its fingers closing across the peg (along y),
and the axis of actuation is the peg/hole axis x. Moving along it the open fingers
slide over the peg - tip, thin section, centre, shoulder, thick section - so *where
the gripper closes along this axis is the grasp choice*, and moving forward while
holding the peg is the insertion. The fixed part of the controller holds the grip
point at y = 0 and z = 0.02 (the peg's axis) and the hand's orientation; the policy
only commands the velocity along x and the grip force. Geometry makes the paper's
point: the thin section fits the hole, the fingers (20 mm wide pads) do not, so a
grasp anywhere on the thin section - at the peg centre, which the grasp reward
prefers, included - stops with the pads against the block face about 30 mm short of
full insertion; a grasp on the thick section lets the peg go in until its shoulder
meets the face (full insertion). The fingers start over or just in front of the peg's
tip, so the greedy grasp (the centre) is the nearer one. The gripper's x is kept in
[0.425, 0.61]: far enough back to reach the thick section at every reset, not so far
that the fingers could get behind the peg and shove it in without a grasp.

Actions, in [-1, 1]^2:
  a[0]: end-effector velocity along the axis of actuation (x), times ``v_max``
        (0.15 m/s): positive towards the hole.
  a[1]: gripper force on each finger, times 70 N: positive closes, negative opens.

Controller, inside the compiled step: damped-least-squares IK on the grip site's
Jacobian (6 x 7, lambda 0.01) turns the Cartesian twist [a0 v_max, k e_y, k e_z,
k e_rot] (k = 40 / s holds y, z and orientation) plus a null-space pull towards a
home posture into joint velocities, which joint velocity servos track (kv 50 N m s
on joints 1-4, 10 on 5-7, the Panda's torque limits; arm gravity is compensated).
The twist is computed once per control step (``n_substeps`` = 10 physics steps of
2 ms, i.e. 50 Hz); the servos act every physics step.

Controller of the "hand" model: the same clipped x-velocity goes straight to a velocity
servo on the hand's slide joint (kv 800 N s/m, force limit 57 N, slide armature 7.5 kg:
the arm's servo damping, push limit and inertia along x at the grip point).

Observation (float32[41]): grip point position (3), hand orientation quaternion (4),
grip point linear (3) and angular (3) velocity (the hand model: the slide's velocity
along x, and zeros); peg centre position (3), quaternion
(4), linear (3) and angular (3, peg frame) velocity; hole mouth position (3) and
orientation (4; the block is fixed, so its velocities are identically zero and left
out); finger opening and its rate (2); peg centre minus grip point (3); inserted
position minus peg centre (3).

Rewards (docs/peg.md; k = ``reward_k`` = 20 / m):
  stage 0 (grasp):  R_1 = exp(-k |grip - peg centre|),      R_2 = 0
  stage 1 (insert): R_1 = 1,  R_2 = exp(-k |peg centre - inserted position|)
  success:          R_1 = R_2 = 1, episode done.
The inserted position is where the peg's centre is when the shoulder sits on the
block face: (0.62, 0, 0.02). Success: stage 1 and the centre within ``success_tol``
(4 mm) of it. Stage 0 -> 1 on a stable grasp: both finger pads touching the peg
while the gripper is commanded to close with at least ``grasp_close_min`` (0.2, i.e.
14 N), for ``grasp_hold_steps`` (3) consecutive control steps. The stage never
decreases (a later regrasp is allowed; it does not change the stage).

Metrics (at an evaluation episode's end, in the rows' ``eval_end``): ``success``, and where
the grasp that handed over holds the peg (`grasp_metrics`): ``grasp_thick`` (pads wholly
on the thick section, the grasp that can insert) and ``grasp_thin`` (any other); both 0
for an episode that never grasped, so their sum is the hand-over rate. ``hold_thick``: the
pads hold the thick section at the episode's end (a regrasp after the hand-over shows here).

Reset randomisation (uniform, documented and tested):
  peg gap (tip to block face)  [0.020, 0.050] m  -> peg centre x in [0.470, 0.500]
  peg y offset                 [-0.004, 0.004] m
  peg yaw                      [-5, 5] degrees
  grip point start x           [0.570, 0.585] m  (fingers open, 40 mm each)

Physics: timestep 2 ms, implicitfast, Newton with 12 iterations and 10 line-search
iterations, pyramidal cones. Measured here: with 6/6 or 4/4 iterations (4/4 is 1.4x
faster) the batched test rollouts break (pegs flung out of the grasp, missed grasps);
12/10 passes them all, with MJX matching C MuJoCo. Only 13 explicit contact pairs:
pads-peg (4), table-peg (2), hole boxes-thin section (4), block face-{thick section,
pads} (3). If the state ever
becomes non-finite the episode ends as a truncation and the observation is zeroed.
On CPU, run with ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false`` (see
``cpu_xla_flags``); with it this env steps ~50x faster on
CPU (measured: 138 vs 2.7 control steps/s, one env, same machine and load).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Sequence

if "mujoco" not in sys.modules and not os.environ.get("MUJOCO_GL") and not (
    os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
):
    # Headless: MuJoCo's default GL backend (GLFW) needs a display; EGL does not.
    os.environ["MUJOCO_GL"] = "egl"

import jax
import jax.numpy as jnp
import numpy as np

try:
    import mujoco
except Exception as _err:  # mujoco picks its GL backend at import; a broken one fails right here
    if os.environ.get("MUJOCO_GL", "").lower() == "osmesa":
        raise ImportError(
            "mujoco failed to import with MUJOCO_GL=osmesa: OSMesa is missing (on Debian/Ubuntu: "
            "`apt-get install libosmesa6`), or use MUJOCO_GL=egl. Cause: " + repr(_err)
        ) from _err
    raise
from brax.envs.base import Env, State
from flax import struct

from envs_mjx import warn_if_cpu_unconfigured
from envs_mjx.frames import mujoco_frames
from envs_mjx.peg_c import CPhysics
from mujoco import mjx

ASSET = Path(__file__).resolve().parent / "assets" / "panda_peg.xml"
HAND_ASSET = Path(__file__).resolve().parent / "assets" / "hand_peg.xml"
MODELS = ("arm", "hand")  # the robot models (``PegInHole(model=...)``)
PHYSICS = ("mjx", "c")  # what steps the physics (``PegInHole(physics=...)``): MuJoCo MJX, or C MuJoCo

# Scene constants (must match the XML).
HOLE_FACE_X = 0.60
AXIS_Z = 0.02  # the hole's and the resting peg's axis height
PEG_HALF = 0.08  # half of the peg's length (centre to tip / to back)
THIN_LEN = 0.10  # shoulder to tip
CENTRE_TO_SHOULDER = 0.02
THICK_LEN = 0.06
PAD_HALF_X = 0.01
INSERTED = np.array([HOLE_FACE_X + CENTRE_TO_SHOULDER, 0.0, AXIS_Z])
HOLE_MOUTH = np.array([HOLE_FACE_X, 0.0, AXIS_Z])

# Reset ranges (uniform).
GAP_RANGE = (0.020, 0.050)
PEG_Y_RANGE = (-0.004, 0.004)
PEG_YAW_RANGE = (-np.deg2rad(5.0), np.deg2rad(5.0))
GRIP_X0_RANGE = (0.570, 0.585)
# The grip point's x is kept in this range (soft limit on the commanded velocity).
GRIP_X_LIMITS = (HOLE_FACE_X - 0.175, HOLE_FACE_X + 0.01)

# Observation layout (float32[41]).
OBS_SLICES = {
    "grip_pos": slice(0, 3), "hand_quat": slice(3, 7), "grip_linvel": slice(7, 10), "grip_angvel": slice(10, 13),
    "peg_pos": slice(13, 16), "peg_quat": slice(16, 20), "peg_linvel": slice(20, 23), "peg_angvel": slice(23, 26),
    "hole_pos": slice(26, 29), "hole_quat": slice(29, 33), "finger_opening": slice(33, 34),
    "finger_rate": slice(34, 35), "peg_minus_grip": slice(35, 38), "inserted_minus_peg": slice(38, 41),
}
_HAND_R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # fingers down, close along y
_Q_SEED = np.array([0.0, 0.5, 0.0, -2.3, 0.0, 2.8, 0.785])


def _rot_err(R: Any, R_t: Any, xp=jnp):
    """Rotation vector (small-angle) taking R to R_t, in the world frame."""
    return 0.5 * xp.sum(xp.cross(R.T, R_t.T), axis=0)


def _solve_start_postures(m: mujoco.MjModel, xs: np.ndarray, grip_site: int) -> np.ndarray:
    """Arm joint angles putting the grip point at (x, 0, AXIS_Z) with the hand down, per x."""
    d = mujoco.MjData(m)
    out, q = [], _Q_SEED.copy()
    jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    for x in xs:
        target = np.array([x, 0.0, AXIS_Z])
        for _ in range(200):
            d.qpos[:7] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            err = np.r_[target - d.site_xpos[grip_site], _rot_err(d.site_xmat[grip_site].reshape(3, 3), _HAND_R, np)]
            if np.linalg.norm(err) < 1e-10:
                break
            mujoco.mj_jacSite(m, d, jp, jr, grip_site)
            J = np.r_[jp, jr][:, :7]
            q = q + J.T @ np.linalg.solve(J @ J.T + 1e-6 * np.eye(6), err)
        if np.linalg.norm(err) > 1e-6:
            raise RuntimeError(f"IK for the start posture at x={x:.3f} did not converge ({err})")
        out.append(q.copy())
    return np.stack(out)


@struct.dataclass
class Readout:
    """What the env's controller, observation, rewards and grasp check read of the physics, float32.

    Either physics fills it: MJX from its ``mjx.Data`` (`PegInHole.readout`), C MuJoCo through the callback
    (`envs_mjx.peg_c`). As in the data a physics step leaves, positions, rotations, contacts and the
    Jacobian are those of the last substep's forward pass (before its integration), qpos and qvel after it.
    """

    qpos: jax.Array  # [nq]
    qvel: jax.Array  # [nv]
    ctrl: jax.Array  # [nu]: the commands the physics step ran with (zeros at reset)
    grip_pos: jax.Array  # [3]: the grip site
    grip_mat: jax.Array  # [3, 3]: the grip site's rotation
    peg_pos: jax.Array  # [3]: the peg body (its centre)
    hand_quat: jax.Array  # [4]: the hand body
    tip_pos: jax.Array  # [3]: the peg tip site
    touch: jax.Array  # bool[2]: the left / right pad touches the peg (penetrating or < 0.5 mm apart)
    jac: jax.Array | None  # [6, 7]: the grip site's Jacobian w.r.t. the arm's joints (None for the hand)


@struct.dataclass
class CData:
    """The pipeline state of ``physics="c"``: C MuJoCo's complete float64 state as uint32 words (`envs_mjx.peg_c`)
    and its float32 readout. ``qpos``, ``qvel`` and ``ctrl`` are the readout's, as on an ``mjx.Data``."""

    state: jax.Array  # uint32[2 * mj_stateSize(mjSTATE_INTEGRATION)]
    readout: Readout

    @property
    def qpos(self) -> jax.Array:
        return self.readout.qpos

    @property
    def qvel(self) -> jax.Array:
        return self.readout.qvel

    @property
    def ctrl(self) -> jax.Array:
        return self.readout.ctrl


def _jacobian(d: Any, arm_v: np.ndarray, hand_root: int, point: jax.Array) -> jax.Array:
    """6 x 7 Jacobian of a point on the hand w.r.t. the arm joints (all ancestors of the hand)."""
    cdof = d.cdof[arm_v]
    offset = point - d.subtree_com[hand_root]
    jacp = cdof[:, 3:] + jnp.cross(cdof[:, :3], offset)
    return jnp.concatenate([jacp.T, cdof[:, :3].T], axis=0)


class _ArmDrive:
    """The Panda arm: start postures by IK, and DLS IK + joint velocity servos that move the grip point along x
    while holding y, z and the hand's orientation (the module doc's "Controller")."""

    asset = ASSET

    def __init__(self, m: mujoco.MjModel, grip: int, hold_gain: float):
        jid = lambda n: m.joint(n).id  # noqa: E731
        self.robot_q = np.array([m.jnt_qposadr[jid(f"joint{i}")] for i in range(1, 8)])
        self.robot_v = np.array([m.jnt_dofadr[jid(f"joint{i}")] for i in range(1, 8)])
        assert list(self.robot_q) == list(range(7)) and list(self.robot_v) == list(range(7))
        self.grip, self.hold_gain = grip, hold_gain
        self.hand_root = int(m.body_rootid[m.body("hand").id])
        # Start postures on a grid of grip x (interpolated at reset) and the home posture.
        self.x_grid = np.linspace(GRIP_X0_RANGE[0] - 0.005, GRIP_X0_RANGE[1] + 0.005, 9)
        self.q_grid = _solve_start_postures(m, self.x_grid, grip)
        self.q_home = _solve_start_postures(m, np.array([0.50]), grip)[0]
        self.limits = np.asarray(m.actuator_ctrlrange[:7, 1])
        self.hand_R = jnp.asarray(_HAND_R)

    def start_qpos(self, qpos: jax.Array, x0: jax.Array) -> jax.Array:
        """``qpos`` with the arm in the start posture whose grip point is at (x0, 0, AXIS_Z)."""
        q_arm = jax.vmap(lambda col: jnp.interp(x0, self.x_grid, col), in_axes=1)(jnp.asarray(self.q_grid))
        return qpos.at[self.robot_q].set(q_arm)

    @property
    def jac_dofs(self) -> np.ndarray:
        """The dofs whose grip-site Jacobian the readout carries: the arm's joints."""
        return self.robot_v

    def mjx_jacobian(self, d: Any) -> jax.Array:
        """The grip site's Jacobian [6, 7] w.r.t. the arm's joints, from an ``mjx.Data``."""
        return _jacobian(d, self.robot_v, self.hand_root, d.site_xpos[self.grip])

    def control(self, ro: Readout, vx: jax.Array) -> jax.Array:
        """Joint velocity commands, float32[7], moving the grip point at ``vx`` along x."""
        p, R, J = ro.grip_pos, ro.grip_mat, ro.jac
        k = self.hold_gain
        twist = jnp.concatenate([jnp.stack([vx, k * (0.0 - p[1]), k * (AXIS_Z - p[2])]),
                                 k * _rot_err(R, self.hand_R)])
        JJt = J @ J.T + 1e-4 * jnp.eye(6)
        Jpinv = J.T @ jnp.linalg.solve(JJt, jnp.eye(6))
        q = ro.qpos[self.robot_q]
        qdot = Jpinv @ twist + (jnp.eye(7) - Jpinv @ J) @ (2.0 * (jnp.asarray(self.q_home) - q))
        return jnp.clip(qdot, -self.limits, self.limits)

    def grip_velocity(self, ro: Readout) -> jax.Array:
        """The grip point's linear and angular velocity, float32[6], world frame."""
        return ro.jac @ ro.qvel[self.robot_v]


class _HandDrive:
    """The Franka Hand on a slide along x: the slide's position is the grip point's x, its servo takes the
    commanded x-velocity as it is; y, z and orientation are fixed by construction."""

    asset = HAND_ASSET

    def __init__(self, m: mujoco.MjModel, grip: int, hold_gain: float):
        del grip, hold_gain  # nothing to hold: the model has no other degree of freedom
        self.robot_q = np.array([m.jnt_qposadr[m.joint("hand_x").id]])
        self.robot_v = np.array([m.jnt_dofadr[m.joint("hand_x").id]])

    def start_qpos(self, qpos: jax.Array, x0: jax.Array) -> jax.Array:
        """``qpos`` with the grip point at (x0, 0, AXIS_Z)."""
        return qpos.at[self.robot_q].set(x0)

    jac_dofs = np.zeros(0, int)  # the controller needs no Jacobian

    def mjx_jacobian(self, d: Any) -> None:
        del d

    def control(self, ro: Readout, vx: jax.Array) -> jax.Array:
        """The slide servo's velocity command, float32[1]."""
        del ro
        return vx[None]

    def grip_velocity(self, ro: Readout) -> jax.Array:
        """The grip point's linear and angular velocity, float32[6]: the slide's along x, zeros else."""
        return jnp.zeros(6).at[0].set(ro.qvel[self.robot_v[0]])


class PegInHole(Env):
    """Grasp a two-section peg with a Panda and insert it (2 stages). See the module doc.

    ``model``: "arm" (the Panda arm with the Franka Hand) or "hand" (the hand alone on a slide); ``MODELS``.
    ``physics``: "mjx" (MuJoCo MJX, runs on any JAX device) or "c" (C MuJoCo on the host behind
    `jax.pure_callback`, 10x and more faster on a CPU; `envs_mjx.peg_c`, docs/peg.md#c-physics); ``PHYSICS``.
    The task is the same on both: only the physics step and the forward pass behind the `Readout` move.
    ``grip_held``: from the hand-over on, the gripper closes with full force whatever a[1] commands, so the
    grasp that handed over is the one that inserts. Not the paper's task (its insertion agent commands the
    gripper and may regrasp): a diagnostic of whether the first agent's grasp is cooperative
    (docs/peg.md#the-grip-held-variant).
    """

    def __init__(
        self,
        episode_length: int = 1000,
        n_substeps: int = 10,
        v_max: float = 0.15,
        reward_k: float = 20.0,
        success_tol: float = 0.004,
        grasp_hold_steps: int = 3,
        grasp_close_min: float = 0.2,
        hold_gain: float = 40.0,
        randomise: bool = True,
        solver_iterations: int | None = None,
        solver_ls_iterations: int | None = None,
        model: str = "arm",
        physics: str = "mjx",
        grip_held: bool = False,
    ):
        if model not in MODELS:
            raise ValueError(f"model: unknown robot model {model!r}; choose one of {MODELS}")
        if physics not in PHYSICS:
            raise ValueError(f"physics: unknown physics {physics!r}; choose one of {PHYSICS}")
        self.model, self.physics = model, physics
        self.episode_length = int(episode_length)
        self.n_substeps = int(n_substeps)
        self.v_max = float(v_max)
        self.reward_k = float(reward_k)
        self.success_tol = float(success_tol)
        self.grasp_hold_steps = int(grasp_hold_steps)
        self.grasp_close_min = float(grasp_close_min)
        self.hold_gain = float(hold_gain)
        self.randomise = bool(randomise)
        self.grip_held = bool(grip_held)
        self.num_stages = 2

        drive_cls = _ArmDrive if model == "arm" else _HandDrive
        m = mujoco.MjModel.from_xml_path(str(drive_cls.asset))
        if solver_iterations is not None:
            m.opt.iterations = int(solver_iterations)
        if solver_ls_iterations is not None:
            m.opt.ls_iterations = int(solver_ls_iterations)
        self.mj_model = m
        self.dt = float(m.opt.timestep) * self.n_substeps

        # Indices (static).
        jid = lambda n: m.joint(n).id  # noqa: E731
        self._fing_q = np.array([m.jnt_qposadr[jid(n)] for n in ("finger_left", "finger_right")])
        self._fing_v = np.array([m.jnt_dofadr[jid(n)] for n in ("finger_left", "finger_right")])
        self._peg_q = int(m.jnt_qposadr[jid("peg")])
        self._peg_v = int(m.jnt_dofadr[jid("peg")])
        self._grip = m.site("grip").id
        self._hand = m.body("hand").id
        self._peg_body = m.body("peg").id
        self._drive = drive_cls(m, self._grip, self.hold_gain)
        self._robot_q = self._drive.robot_q  # the robot's joints in qpos: the arm's 7, or the hand's slide

        self.sys = mjx.put_model(m)
        d0 = mjx.make_data(self.sys)
        self._data0 = d0

        # Geom ids for grasp detection (contact slots are matched by geom id at run time).
        self._pad_l, self._pad_r = m.geom("pad_left").id, m.geom("pad_right").id
        self._peg_geoms = np.array([m.geom("peg_thick").id, m.geom("peg_thin").id])

        self._tip = m.site("peg_tip").id
        self._c = None if physics == "mjx" else CPhysics(
            m, self.n_substeps, self._grip, self._tip, self._peg_body, self._hand, (self._pad_l, self._pad_r),
            self._peg_geoms, self._drive.jac_dofs)

        self._inserted = jnp.asarray(INSERTED, jnp.float32)
        self._hole_obs = jnp.asarray(np.r_[HOLE_MOUTH, 1.0, 0.0, 0.0, 0.0], jnp.float32)
        if physics == "mjx":
            warn_if_cpu_unconfigured("PegInHole", "about 50x")

    # ----- brax Env API -------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return 41

    @property
    def action_size(self) -> int:
        return 2

    @property
    def backend(self) -> str:
        """"mjx", or "c" for C MuJoCo (then no MJX runs in the env's programs: `envs_mjx.cpu_compiler_options`)."""
        return self.physics

    def reset(self, rng: jax.Array) -> State:
        k_gap, k_y, k_yaw, k_x = jax.random.split(rng, 4)
        r = self.randomise

        def u(k, lo_hi):
            lo, hi = lo_hi
            return jax.random.uniform(k, (), minval=lo, maxval=hi) if r else jnp.float32((lo + hi) / 2)

        gap, dy, yaw, x0 = u(k_gap, GAP_RANGE), u(k_y, PEG_Y_RANGE), u(k_yaw, PEG_YAW_RANGE), u(k_x, GRIP_X0_RANGE)
        centre = jnp.stack([HOLE_FACE_X - gap - PEG_HALF, dy, jnp.float32(AXIS_Z)])
        quat = jnp.stack([jnp.cos(yaw / 2), 0.0, 0.0, jnp.sin(yaw / 2)])
        qpos = jnp.zeros(self.mj_model.nq)
        qpos = self._drive.start_qpos(qpos, x0).at[self._fing_q].set(0.04)
        qpos = qpos.at[self._peg_q:self._peg_q + 3].set(centre).at[self._peg_q + 3:self._peg_q + 7].set(quat)
        ctrl = jnp.zeros(self.mj_model.nu)
        if self._c is None:
            data = self._data0.replace(qpos=qpos, qvel=jnp.zeros(self.mj_model.nv), ctrl=ctrl)
            data = mjx.forward(self.sys, data)
        else:
            bits, flat = self._c.reset(qpos)
            data = CData(state=bits, readout=Readout(ctrl=ctrl, **self._c.unpack(flat)))
        ro = self.readout(data)

        stage = jnp.int32(0)
        rewards = self._rewards(stage, ro.grip_pos, ro.peg_pos, jnp.bool_(False))
        info = {
            "stage": stage,
            "rewards": rewards,
            "truncation": jnp.float32(0.0),
            "steps": jnp.int32(0),
            "grasp_count": jnp.int32(0),
            "grasp_offset": jnp.float32(0.0),
        }
        metrics = {"success": jnp.float32(0.0), **grasp_metrics(stage, jnp.float32(0.0), jnp.bool_(False),
                                                                 jnp.float32(0.0))}
        obs = self._obs(ro)
        return State(pipeline_state=data, obs=obs, reward=rewards.sum(), done=jnp.float32(0.0),
                     metrics=metrics, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        action = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        if self.grip_held:  # after the hand-over the gripper closes whatever a[1] says: no regrasp
            action = action.at[1].set(jnp.where(state.info["stage"] >= 1, 1.0, action[1]))
        ctrl = self._control(self.readout(state.pipeline_state), action)
        d = self._physics_step(state.pipeline_state, ctrl)
        ro = self.readout(d)

        finite = jnp.all(jnp.isfinite(ro.qpos)) & jnp.all(jnp.isfinite(ro.qvel)) & jnp.all(jnp.abs(ro.qvel) < 1e3)
        grip, c = ro.grip_pos, ro.peg_pos

        # Stable grasp: both pads touching the peg while closing, for grasp_hold_steps steps.
        grasping = ro.touch[0] & ro.touch[1] & (action[1] >= self.grasp_close_min)
        count = jnp.where(grasping, state.info["grasp_count"] + 1, 0)
        stage = jnp.maximum(state.info["stage"], (count >= self.grasp_hold_steps).astype(jnp.int32))
        # Where along the peg the hand-over grasp holds it: the grip point's x from the peg's centre, at the step the
        # grasp is recognised (kept for the rest of the episode).
        offset = jnp.where(stage > state.info["stage"], grip[0] - c[0], state.info["grasp_offset"])

        inserted = (stage >= 1) & (jnp.linalg.norm(c - self._inserted) < self.success_tol) & finite
        rewards = self._rewards(stage, grip, c, inserted)
        steps = state.info["steps"] + 1
        success = inserted.astype(jnp.float32)
        timeout = ((steps >= self.episode_length) | ~finite).astype(jnp.float32)
        done = jnp.maximum(success, timeout)
        obs = jnp.where(finite, self._obs(ro), 0.0)
        rewards = jnp.where(finite, rewards, 0.0)
        info = {
            "stage": stage,
            "rewards": rewards,
            "truncation": timeout * (1.0 - success),
            "steps": steps,
            "grasp_count": count,
            "grasp_offset": offset,
        }
        return State(pipeline_state=d, obs=obs, reward=rewards.sum(), done=done,
                     metrics={"success": success, **grasp_metrics(stage, offset, ro.touch[0] & ro.touch[1],
                                                                  grip[0] - c[0])}, info=info)

    # ----- the physics: MJX or C, and what the env reads of it -------------------------
    def _physics_step(self, d: Any, ctrl: jax.Array) -> Any:
        """``n_substeps`` physics steps under ``ctrl`` float32[nu]: the next pipeline state."""
        if self._c is None:
            d = d.replace(ctrl=ctrl)
            return jax.lax.fori_loop(0, self.n_substeps, lambda _, x: mjx.step(self.sys, x), d)
        bits, flat = self._c.step(d.state, ctrl)
        return CData(state=bits, readout=Readout(ctrl=ctrl, **self._c.unpack(flat)))

    def readout(self, d: Any) -> Readout:
        """The `Readout` of one pipeline state (an ``mjx.Data``, or `CData` whose readout it carries)."""
        if isinstance(d, CData):
            return d.readout
        touch_l, touch_r = self._pad_contacts(d)
        return Readout(qpos=d.qpos, qvel=d.qvel, ctrl=d.ctrl, grip_pos=d.site_xpos[self._grip],
                       grip_mat=d.site_xmat[self._grip].reshape(3, 3), peg_pos=d.xpos[self._peg_body],
                       hand_quat=d.xquat[self._hand], tip_pos=d.site_xpos[self._tip],
                       touch=jnp.stack([touch_l, touch_r]), jac=self._drive.mjx_jacobian(d))

    # ----- pieces -------------------------------------------------------------------
    def _rewards(self, stage, grip, c, inserted):
        r1 = jnp.where(stage >= 1, 1.0, jnp.exp(-self.reward_k * jnp.linalg.norm(grip - c)))
        r2 = jnp.where(stage >= 1, jnp.exp(-self.reward_k * jnp.linalg.norm(c - self._inserted)), 0.0)
        r = jnp.stack([r1, r2])
        return jnp.where(inserted, 1.0, r).astype(jnp.float32)

    def _pad_contacts(self, d):
        """Whether the left / right finger pad touches the peg (penetration or < 0.5 mm gap)."""
        con = d._impl.contact
        g0, g1 = con.geom[:, 0], con.geom[:, 1]
        near = con.dist < 5e-4
        on_peg0, on_peg1 = jnp.isin(g0, self._peg_geoms), jnp.isin(g1, self._peg_geoms)

        def touch(pad):
            return jnp.any(near & (((g0 == pad) & on_peg1) | ((g1 == pad) & on_peg0)))

        return touch(self._pad_l), touch(self._pad_r)

    def _control(self, ro: Readout, action: jax.Array) -> jax.Array:
        """ctrl float32[nu]: the robot's commands (the arm's 7 joint velocities or the hand's slide velocity), then
        the gripper's (-a[1]: its motor's +1 opens)."""
        x = ro.grip_pos[0]
        lo, hi = GRIP_X_LIMITS
        vx = jnp.clip(action[0] * self.v_max, (lo - x) / 0.1, (hi - x) / 0.1)
        return jnp.concatenate([self._drive.control(ro, vx), -action[1:2]])

    def _obs(self, ro: Readout) -> jax.Array:
        """The observation float32[41] (module doc; ``OBS_SLICES``)."""
        grip, c = ro.grip_pos, ro.peg_pos
        ee_vel = self._drive.grip_velocity(ro)
        hand_quat = ro.hand_quat
        peg_quat = ro.qpos[self._peg_q + 3:self._peg_q + 7]
        peg_vel = ro.qvel[self._peg_v:self._peg_v + 6]
        opening = jnp.sum(ro.qpos[self._fing_q])[None]
        opening_rate = jnp.sum(ro.qvel[self._fing_v])[None]
        return jnp.concatenate([
            grip, hand_quat, ee_vel,
            c, peg_quat, peg_vel,
            self._hole_obs,
            opening, opening_rate,
            c - grip, self._inserted - c,
        ]).astype(jnp.float32)

    # ----- helpers for tests, scripted controllers and the C simulator -------------
    def peg_depth(self, data) -> jax.Array:
        """How far the thin section's tip is past the block face (full insertion: 0.10 m), of one pipeline state."""
        return self.readout(data).tip_pos[0] - HOLE_FACE_X

    def grip_x(self, data) -> jax.Array:
        return self.readout(data).grip_pos[0]

    def peg_centre(self, data) -> jax.Array:
        return self.readout(data).peg_pos

    def exact_qpos(self, pipeline_states: Any) -> np.ndarray:
        """qpos [..., nq] of pipeline states with any leading axes, on the host: C MuJoCo's float64 qpos from
        the carried state bits, or MJX's float32 qpos."""
        if isinstance(pipeline_states, CData):
            return self._c.state_qpos(np.asarray(pipeline_states.state))
        return np.asarray(pipeline_states.qpos)

    def render_frames(self, states: State) -> np.ndarray:
        """The contract's render hook: one episode's stacked states (leaves [T, ...]) as MuJoCo frames from the
        "side" camera, uint8[T, 240, 320, 3] (`render_frames`)."""
        return render_frames(self, self.exact_qpos(states.pipeline_state))


# ----- episode-end diagnostics ---------------------------------------------------------
def grasp_metrics(stage: jax.Array, offset: jax.Array, holding: jax.Array, now: jax.Array) -> dict[str, jax.Array]:
    """The episode-end diagnostics of where the gripper holds the peg (float32[] each, 0 or 1).

    `grasp_thick` / `grasp_thin`: the grasp that handed over (``offset``, the grip point's x from the peg's centre
    when the grasp was recognised, `info['grasp_offset']`) held the thick section with the pads wholly behind the
    shoulder (the grasp that can insert fully), or not; both 0 before a grasp. `hold_thick`: both pads touch the
    peg now (``holding``) with the grip point ``now`` (x from the peg's centre) that far back: a regrasp after
    the hand-over shows here, not in the first two."""
    thick = -(CENTRE_TO_SHOULDER + PAD_HALF_X)
    grasped = stage >= 1
    return {"grasp_thick": (grasped & (offset <= thick)).astype(jnp.float32),
            "grasp_thin": (grasped & (offset > thick)).astype(jnp.float32),
            "hold_thick": (holding & (now <= thick)).astype(jnp.float32)}


# ----- scripted controllers (tests, benchmarks) ------------------------------------------
def reachable_grip_x(x: jax.Array) -> jax.Array:
    """``x``, or the gripper's backmost reachable x where ``x`` lies behind it."""
    return jnp.maximum(x, GRIP_X_LIMITS[0] + 0.004)


def thick_grasp_x(peg_x: jax.Array) -> jax.Array:
    """The grip point's x for a grasp in the middle of the thick section (0.05 m behind the peg centre at
    ``peg_x``), or as far back as the gripper reaches, which always leaves >= 15 mm of box to hold."""
    return reachable_grip_x(peg_x - (CENTRE_TO_SHOULDER + THICK_LEN / 2))


def scripted_action(state: State, policy: jax.Array, key: jax.Array) -> jax.Array:
    """A scripted controller's action, float32[2], pure JAX (vmap over ``policy`` to mix them).

    ``policy``: 0 grasps the middle of the thick section (0.05 m behind the peg centre, or as far back
    as the gripper reaches, which always leaves >= 15 mm of box to hold) and pushes on: full insertion;
    1 grasps the peg centre, the grasp reward's greedy choice, and pushes on: stalls short; 2 grasps
    the thick section, then opens and slides on: the peg stays; 3 acts uniformly at random (``key``);
    4 grasps the peg centre, then regrasps: opens, moves back to the thick section, closes and pushes on
    (the insertion agent may command the gripper, so a thin hand-over can still insert; not with
    ``grip_held``).
    """
    o, stage = state.obs, state.info["stage"]
    grip_x, peg_x = o[OBS_SLICES["grip_pos"]][0], o[OBS_SLICES["peg_pos"]][0]
    opening = o[OBS_SLICES["finger_opening"]][0]
    thick = thick_grasp_x(peg_x)
    target = jnp.where((policy == 1) | (policy == 4), reachable_grip_x(peg_x), thick)
    err = target - grip_x
    closing = (jnp.abs(err) < 0.003) | (opening < 0.075)
    grasp = jnp.stack([jnp.where(closing, 0.0, jnp.clip(err / 0.02, -1.0, 1.0)), jnp.where(closing, 1.0, -1.0)])
    after = jnp.where(policy == 2, jnp.array([1.0, -1.0]), jnp.array([1.0, 1.0]))  # release: open, slide on
    # The regrasp, from the thick target's distance alone: far from it, open fully, then move; there, close,
    # then push once closed on the 40 mm box.
    to_thick = thick - grip_x
    regrasp = jnp.where(jnp.abs(to_thick) > 0.004,
                        jnp.stack([jnp.where(opening > 0.075, jnp.clip(to_thick / 0.02, -1.0, 1.0), 0.0), -1.0]),
                        jnp.stack([jnp.where(opening < 0.045, 1.0, 0.0), 1.0]))
    after = jnp.where(policy == 4, regrasp, after)
    act = jnp.where(stage >= 1, after, grasp)
    return jnp.where(policy == 3, jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0), act)


# ----- offscreen rendering -------------------------------------------------------------
def render_frames(
    env: PegInHole,
    pipeline_states: Any,
    camera: str | int = "side",
    height: int = 240,
    width: int = 320,
) -> np.ndarray:
    """Render MJX states to uint8 RGB frames, shape [T, height, width, 3] (`envs_mjx.frames.mujoco_frames`).

    ``pipeline_states``: a sequence of ``mjx.Data``, `CData` (or ``mujoco.MjData``), or one
    ``mjx.Data`` or `CData` whose leaves have a leading time axis (e.g. the stacked
    ``state.pipeline_state`` of a ``lax.scan`` rollout of one environment), or an
    array of qpos, shape [T, nq].
    Cameras in the scene: "side" (close-up of peg and hole), "wide", "top".
    """
    if isinstance(pipeline_states, (list, tuple)):
        qpos = np.stack([env.exact_qpos(s) if isinstance(s, CData) else np.asarray(s.qpos) for s in pipeline_states])
    elif isinstance(pipeline_states, CData):
        qpos = env.exact_qpos(pipeline_states)
    elif hasattr(pipeline_states, "qpos"):
        qpos = np.asarray(pipeline_states.qpos)
    else:  # an array of qpos
        qpos = np.asarray(pipeline_states)
    return mujoco_frames(env.mj_model, qpos, camera, height, width)


def simulate_c(env: PegInHole, qpos0: np.ndarray, ctrls: Sequence[np.ndarray]) -> np.ndarray:
    """Replay per-control-step ``ctrls`` in the C simulator from ``qpos0``; qpos after each step.

    Uses the same model, ``n_substeps`` and zero initial velocity as the env, so an MJX
    rollout's recorded ``pipeline_state.ctrl`` can be compared with C MuJoCo.
    """
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    mujoco.mj_forward(m, d)
    out = []
    for u in ctrls:
        d.ctrl[:] = u
        mujoco.mj_step(m, d, nstep=env.n_substeps)
        out.append(d.qpos.copy())
    return np.stack(out)
