"""N-room maze with a differential-drive robot and a dead-end pocket behind every inner wall.

Layout (docs/design.md#environments-and-their-contract). Rooms are 5 m x 5 m, left to right: room k spans x in [5k, 5k + 5],
y in [0, 5]. The inner wall at x_k = 5k (k = 1 .. N-1) has two 1 m doors, y in [1, 2]
(low) and [3, 4] (high). One of them is a dead end: behind it, in room k, a pocket
2 m deep closed at mid-height (y = 2.5). The dead end is the low door for odd k and the
high door for even k, so the door straight ahead of where the robot enters a room is
always the trap (the start is bottom-left). The last room has no trap; the goal is
x >= 5N - 0.3.

Physics. The robot is a disk of radius 0.15 m. An action a in [-1, 1]^2 (clipped) gives
linear velocity v = (a[0] + 1) / 2 * v_max (forwards only; `reverse=True`: v = a[0] * v_max,
backwards too) and angular velocity w = a[1] * w_max, held for dt. The heading turns by w * dt; the centre moves along the straight chord
v * dt long at the mid-step heading (midpoint integration). That chord is the swept
path of the step and is checked exactly: the first contact time with any wall is the
first entry of the centre into a capsule (the wall segment grown by the radius), solved
in closed form (two side lines, two end caps). The robot stops `contact_gap` short of
that contact; the rest of the step's chord, less its component into the wall touched, is
moved along the wall with the same contact check, and stops at the next wall (one
collide-and-slide pass; `slide=False`: the robot stays at the contact for the rest of the step). Being exact, it
cannot tunnel at any speed or heading; a centre already inside a capsule (only float
rounding can put it there) is blocked from moving further in.

Observation float32[24]:
  [0:20]  laser scan, beam i at angle heading + 2*pi*i/20 (beam 0 straight ahead), cast
          from the robot centre against the wall segments; distance / 3 m, clipped to [0, 1];
  [20:22] x / (5N), y / 5;
  [22:24] cos(heading), sin(heading).

Stage and rewards. U = max(U, clip(floor(x / 5), 0, N-1)) at the new position, never
decreasing. R_n = 1 for n < U, clip((x - 5n) / 5, 0, 1) for n = U, 0 for n > U; on the
success step every R_n is 1. reward = sum(R).

Metrics: `success`, and `pocket` (1 while the robot is inside a dead-end pocket), which
evaluation reports at each episode's end: where a failing agent is stuck.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from flax import struct


@dataclasses.dataclass(frozen=True)
class MazeGeometry:
    """Static geometry and robot constants of an N-room maze (lengths in m, time in s)."""

    rooms: int
    room_size: float = 5.0
    doors: tuple[tuple[float, float], ...] = ((1.0, 2.0), (3.0, 4.0))  # (low, high) openings in y
    pocket_depth: float = 2.0
    pocket_closure_y: float = 2.5
    robot_radius: float = 0.15
    v_max: float = 1.0
    w_max: float = 2.0
    dt: float = 0.2
    n_beams: int = 20
    beam_range: float = 3.0
    goal_margin: float = 0.3
    start_x: tuple[float, float] = (0.5, 1.0)
    start_y: tuple[float, float] = (1.25, 1.75)
    start_heading: tuple[float, float] = (-math.pi / 4, math.pi / 4)
    # Stop this far (along the path) before touching a wall, so float rounding cannot
    # leave the disk overlapping one.
    contact_gap: float = 1e-3
    # Kinematics the paper leaves open ("linear velocity and angular velocity"). reverse: a[0]
    # in [-1, 1] drives backwards too (v = a[0] v_max); otherwise only forwards, v = (a[0] + 1)/2 v_max,
    # so a policy's zero-mean start already drives. slide: a blocked step spends what is left of
    # it along the wall it touched (one collide-and-slide pass) instead of stopping there.
    # The defaults reproduce the prototype's learning curve (docs/design.md#the-learning-yardstick); the
    # reversing robot (reverse=True, slide=False) is how the maze's early results ran (docs/lab-notes.md).
    reverse: bool = False
    slide: bool = True

    @property
    def width(self) -> float:
        """Total length of the maze along x: 5N."""
        return self.room_size * self.rooms

    @property
    def goal_x(self) -> float:
        """Success threshold on the robot's x: 5N - 0.3."""
        return self.width - self.goal_margin


def dead_end_is_low(wall_k: int) -> bool:
    """Whether the inner wall at x = 5 * wall_k has its dead end behind the low door.

    Odd walls (1, 3, ...) trap the low door, even walls (2, ...) the high one.
    """
    if wall_k < 1:
        raise ValueError(f"wall_k must be >= 1 (inner walls are numbered from 1), got {wall_k}")
    return wall_k % 2 == 1


def maze_walls(geometry: MazeGeometry) -> np.ndarray:
    """Wall segments of the maze, float32[4 + 5(N-1), 4] as rows (x0, y0, x1, y1).

    Order: the 4 outer walls, then per inner wall k = 1 .. N-1 its 3 pieces (bottom,
    middle, top) followed by its pocket's 2 walls (mid-height closure, far side).
    """
    g = geometry
    h, w = g.room_size, g.width
    segs = [(0.0, 0.0, w, 0.0), (w, 0.0, w, h), (w, h, 0.0, h), (0.0, h, 0.0, 0.0)]
    (low0, low1), (high0, high1) = g.doors
    for k in range(1, g.rooms):
        xk = k * h
        segs += [(xk, 0.0, xk, low0), (xk, low1, xk, high0), (xk, high1, xk, h)]
        far = xk + g.pocket_depth
        mid = g.pocket_closure_y
        segs.append((xk, mid, far, mid))
        segs.append((far, 0.0, far, mid) if dead_end_is_low(k) else (far, mid, far, h))
    return np.asarray(segs, dtype=np.float32)


@struct.dataclass
class RobotPose:
    """The robot's pose, kept as `State.pipeline_state` for renderers.

    pos: float32[..., 2] (x, y) in m; heading: float32[...] in rad, wrapped to [-pi, pi).
    """

    pos: jax.Array
    heading: jax.Array

    def qpos(self) -> jax.Array:
        """float32[..., 3], the (slide_x, slide_y, hinge_z) joint positions of `maze_mjcf`."""
        return jnp.concatenate([self.pos, self.heading[..., None]], axis=-1)


def _cross(a: jax.Array, b: jax.Array) -> jax.Array:
    """z component of the 2-D cross product, broadcasting over leading axes."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _ray_distances(origin: jax.Array, angles: jax.Array, walls: jax.Array, max_range: float) -> jax.Array:
    """Distance from `origin` (float32[2]) along each angle (float32[B]) to the nearest wall
    of `walls` (float32[S, 4]), capped at `max_range`. Returns float32[B]."""
    dirs = jnp.stack([jnp.cos(angles), jnp.sin(angles)], axis=-1)[:, None, :]  # [B, 1, 2]
    a, e = walls[:, :2], walls[:, 2:] - walls[:, :2]  # [S, 2]
    to_a = a - origin
    # origin + t * dir = a + s * e, solved by crossing with e and with dir.
    denom = _cross(dirs, e)  # [B, S]
    parallel = jnp.abs(denom) < 1e-9
    safe = jnp.where(parallel, 1.0, denom)
    t = _cross(to_a, e) / safe
    s = _cross(to_a, dirs) / safe
    hit = ~parallel & (t >= 0.0) & (s >= 0.0) & (s <= 1.0)
    return jnp.minimum(jnp.min(jnp.where(hit, t, max_range), axis=-1), max_range)


def _blocked_fraction(t_hit: jax.Array, step_len: jax.Array, gap: float) -> jax.Array:
    """How much of a step's chord (length `step_len`) is moved when first contact is at fraction `t_hit`:
    all of it if there is none, else up to `gap` short of the contact (never behind the start)."""
    return jnp.where(t_hit < 1.0, jnp.maximum(t_hit - gap / jnp.maximum(step_len, 1e-12), 0.0), 1.0)


def _wall_normal(pos: jax.Array, walls: jax.Array) -> jax.Array:
    """Unit vector float32[2] from the point of `walls` (float32[S, 4]) nearest to `pos` towards `pos`:
    the normal of the wall (or wall end) a disk centred at `pos` touches."""
    a, e = walls[:, :2], walls[:, 2:] - walls[:, :2]
    t = jnp.clip(jnp.sum((pos - a) * e, -1) / jnp.sum(e * e, -1), 0.0, 1.0)
    away = pos - (a + t[:, None] * e)  # [S, 2]
    dist = jnp.linalg.norm(away, axis=-1)
    i = jnp.argmin(dist)
    return away[i] / jnp.maximum(dist[i], 1e-12)


def _time_of_impact(pos: jax.Array, disp: jax.Array, walls: jax.Array, radius: float) -> jax.Array:
    """First fraction t in [0, 1] of the straight move pos -> pos + disp (float32[2] each) at
    which a disk of `radius` touches a wall of `walls` (float32[S, 4]); 1 if it never does.

    The disk touches a segment exactly when its centre enters the segment's capsule, the
    union of a rectangle (entered through its two long sides; the short sides lie inside
    the caps) and two end-cap disks. Entry times below 0 (centre already inside) clamp to
    0, which blocks any move that goes further in.
    """
    a, b = walls[:, :2], walls[:, 2:]
    length = jnp.linalg.norm(b - a, axis=-1)  # [S]
    along_dir = (b - a) / length[:, None]
    normal = jnp.stack([-along_dir[:, 1], along_dir[:, 0]], axis=-1)
    rel = pos - a
    # Long sides: signed offset from the segment's line reaches +-radius.
    offset = jnp.sum(rel * normal, axis=-1)
    rate = jnp.sum(disp * normal, axis=-1)
    side = jnp.where(offset >= 0.0, 1.0, -1.0)
    approaching = rate * side < 0.0
    t_side = jnp.maximum((side * radius - offset) / jnp.where(approaching, rate, 1.0), 0.0)
    proj = jnp.sum((rel + t_side[:, None] * disp) * along_dir, axis=-1)
    hit_side = approaching & (proj >= 0.0) & (proj <= length) & (t_side <= 1.0)
    times = [jnp.where(hit_side, t_side, 1.0)]
    # End caps: smaller root of |pos + t * disp - c|^2 = radius^2 while moving towards c.
    qa = jnp.sum(disp * disp)
    for c in (a, b):
        q = pos - c
        qb = jnp.sum(q * disp, axis=-1)
        qc = jnp.sum(q * q, axis=-1) - radius**2
        disc = qb * qb - qa * qc
        t_cap = jnp.maximum((-qb - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.maximum(qa, 1e-12), 0.0)
        hit_cap = (qa > 0.0) & (qb < 0.0) & (disc >= 0.0) & (t_cap <= 1.0)
        times.append(jnp.where(hit_cap, t_cap, 1.0))
    return jnp.min(jnp.stack(times))


class Maze(Env):
    """The N-room maze (docs/design.md#environments-and-their-contract) on the `brax.envs.base.Env` API; pure, jit- and vmap-able.

    Args:
      rooms: N >= 1, the number of rooms and of stages.
      episode_length: steps after which an episode is truncated (>= 1).
      reverse: whether a[0] < 0 drives backwards, or (the default) every a[0] drives forwards.
      slide: whether a blocked step slides along the wall it touched (the default) or stops there.
    """

    def __init__(self, rooms: int = 2, episode_length: int = 1000, reverse: bool = False, slide: bool = True):
        self.geometry = MazeGeometry(rooms=_positive_int("rooms", rooms), reverse=bool(reverse), slide=bool(slide))
        self.episode_length = _positive_int("episode_length", episode_length)
        self._walls = maze_walls(self.geometry)
        g = self.geometry
        self._beam_offsets = (2.0 * np.pi * np.arange(g.n_beams) / g.n_beams).astype(np.float32)

    dead_end_is_low = staticmethod(dead_end_is_low)

    @property
    def walls(self) -> np.ndarray:
        """float32[S, 4] wall segments (x0, y0, x1, y1); see `maze_walls`."""
        return self._walls.copy()

    @property
    def num_stages(self) -> int:
        return self.geometry.rooms

    @property
    def observation_size(self) -> int:
        return self.geometry.n_beams + 4

    @property
    def action_size(self) -> int:
        return 2

    @property
    def backend(self) -> str:
        return "jax"

    def render_frames(self, states: State) -> np.ndarray:
        """The contract's render hook: one episode's stacked states (leaves [T, ...]) drawn top-down,
        uint8[T, H, W, 3] (`envs_mjx.frames.maze_frames`; matplotlib, no OpenGL)."""
        from envs_mjx.frames import maze_frames  # local: matplotlib loads only for videos

        return maze_frames(self, states)

    def reset(self, rng: jax.Array) -> State:
        """A fresh episode at x ~ U[0.5, 1], y ~ U[1.25, 1.75], heading ~ U[-pi/4, pi/4]."""
        g = self.geometry
        kx, ky, kh = jax.random.split(rng, 3)
        pos = jnp.stack([
            jax.random.uniform(kx, (), jnp.float32, *g.start_x),
            jax.random.uniform(ky, (), jnp.float32, *g.start_y),
        ])
        heading = jax.random.uniform(kh, (), jnp.float32, *g.start_heading)
        return self.state_at(pos, heading)

    def state_at(self, pos: jax.Array, heading: jax.Array) -> State:
        """Step 0 of an episode with the robot at `pos` (float32[2]) and `heading` (float32[]).

        The stage starts at the room of `pos`. `pos` must be collision-free and short of the
        goal line; nothing checks it (this runs under jit).
        """
        pose = RobotPose(pos=jnp.asarray(pos, jnp.float32), heading=_wrap(jnp.asarray(heading, jnp.float32)))
        stage, rewards, _ = self._stage_and_rewards(pose.pos[0], jnp.zeros((), jnp.int32))
        zero = jnp.zeros((), jnp.float32)
        return State(
            pipeline_state=pose,
            obs=self._observe(pose),
            reward=jnp.sum(rewards),
            done=zero,
            metrics={"success": zero, "pocket": self.in_pocket(pose.pos)},
            info={"stage": stage, "rewards": rewards, "truncation": zero, "steps": jnp.zeros((), jnp.int32)},
        )

    def step(self, state: State, action: jax.Array) -> State:
        """One dt of motion with `action` float32[2] (clipped to [-1, 1])."""
        g = self.geometry
        pose: RobotPose = state.pipeline_state
        act = jnp.clip(jnp.asarray(action, jnp.float32), -1.0, 1.0)
        v = (act[0] if g.reverse else 0.5 * (act[0] + 1.0)) * g.v_max
        w = act[1] * g.w_max
        mid_heading = pose.heading + 0.5 * w * g.dt
        disp = v * g.dt * jnp.stack([jnp.cos(mid_heading), jnp.sin(mid_heading)])
        walls = jnp.asarray(self._walls)
        t_hit = _time_of_impact(pose.pos, disp, walls, g.robot_radius)
        frac = _blocked_fraction(t_hit, jnp.linalg.norm(disp), g.contact_gap)
        pos = pose.pos + frac * disp
        if g.slide:
            rest = (1.0 - frac) * disp  # zero unless the step was blocked
            normal = _wall_normal(pos, walls)
            along = rest - jnp.minimum(jnp.dot(rest, normal), 0.0) * normal
            t_slide = _time_of_impact(pos, along, walls, g.robot_radius)
            pos = pos + _blocked_fraction(t_slide, jnp.linalg.norm(along), g.contact_gap) * along
        new_pose = RobotPose(pos=pos, heading=_wrap(pose.heading + w * g.dt))

        stage, rewards, success = self._stage_and_rewards(new_pose.pos[0], state.info["stage"])
        steps = state.info["steps"] + 1
        timeout = steps >= self.episode_length
        return state.replace(
            pipeline_state=new_pose,
            obs=self._observe(new_pose),
            reward=jnp.sum(rewards),
            done=(success | timeout).astype(jnp.float32),
            metrics={**state.metrics, "success": success.astype(jnp.float32), "pocket": self.in_pocket(new_pose.pos)},
            info={
                **state.info,
                "stage": stage,
                "rewards": rewards,
                "truncation": (timeout & ~success).astype(jnp.float32),
                "steps": steps,
            },
        )

    def in_pocket(self, pos: jax.Array) -> jax.Array:
        """float32[...]: 1 where the robot's centre (pos [..., 2]) is inside a dead-end pocket, else 0.

        A diagnostic (`state.metrics['pocket']`): an evaluation that ends with the robot
        here took the trap door.
        """
        g = self.geometry
        x, y = pos[..., 0], pos[..., 1]
        room = jnp.floor(x / g.room_size)  # the pocket behind wall k lies in room k
        low = jnp.mod(room, 2) == 1  # dead_end_is_low(k): odd walls trap the low door
        side = jnp.where(low, y < g.pocket_closure_y, y > g.pocket_closure_y)
        return ((room >= 1) & (x - room * g.room_size < g.pocket_depth) & side).astype(jnp.float32)

    def _stage_and_rewards(self, x: jax.Array, prev_stage: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Stage int32[], subtask rewards float32[N] and success bool[] at position x."""
        g = self.geometry
        room = jnp.clip(jnp.floor(x / g.room_size), 0, g.rooms - 1).astype(jnp.int32)
        stage = jnp.maximum(prev_stage, room)
        n = jnp.arange(g.rooms)
        progress = jnp.clip((x - g.room_size * n) / g.room_size, 0.0, 1.0)
        rewards = jnp.where(n < stage, 1.0, jnp.where(n == stage, progress, 0.0))
        success = x >= g.goal_x
        rewards = jnp.where(success, 1.0, rewards).astype(jnp.float32)
        return stage, rewards, success

    def _observe(self, pose: RobotPose) -> jax.Array:
        """float32[24]: scan (20), normalised x and y, cos and sin of the heading."""
        g = self.geometry
        dist = _ray_distances(pose.pos, pose.heading + jnp.asarray(self._beam_offsets), jnp.asarray(self._walls), g.beam_range)
        return jnp.concatenate([
            dist / g.beam_range,
            pose.pos / jnp.array([g.width, g.room_size], jnp.float32),
            jnp.stack([jnp.cos(pose.heading), jnp.sin(pose.heading)]),
        ]).astype(jnp.float32)


def _positive_int(name: str, value) -> int:
    """`value` as an int if it is an integer >= 1 (bools excluded), else ValueError naming `name`."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an int >= 1, got {value!r}")
    return int(value)


def _wrap(angle: jax.Array) -> jax.Array:
    """Angle wrapped to [-pi, pi)."""
    return jnp.mod(angle + jnp.pi, 2.0 * jnp.pi) - jnp.pi


def maze_mjcf(rooms: int) -> str:
    """MJCF of the N-room layout for rendering with MuJoCo.

    Walls are thin boxes named ``wall_<i>`` in the order of `maze_walls`; the goal line is a
    site ``goal``; the robot is a cylinder on joints slide_x, slide_y, hinge_z, so
    ``qpos = RobotPose.qpos()`` places it. Rendering only: the env never simulates this model.
    """
    g = MazeGeometry(rooms=_positive_int("rooms", rooms))
    wall_h, wall_t = 0.5, 0.04  # rendered height and thickness; the env's walls are lines
    cx, cy = g.width / 2, g.room_size / 2
    geoms = []
    for i, (x0, y0, x1, y1) in enumerate(maze_walls(g).tolist()):
        half = 0.5 * math.hypot(x1 - x0, y1 - y0)
        yaw = math.atan2(y1 - y0, x1 - x0)
        geoms.append(
            f'    <geom name="wall_{i}" type="box" material="wall" pos="{(x0 + x1) / 2:.4f} {(y0 + y1) / 2:.4f} {wall_h / 2}" '
            f'size="{half + wall_t / 2:.4f} {wall_t / 2} {wall_h / 2}" euler="0 0 {yaw:.6f}"/>'
        )
    walls_xml = "\n".join(geoms)
    r = g.robot_radius
    return f"""<mujoco model="maze_{rooms}">
  <compiler angle="radian"/>
  <option timestep="{g.dt}"/>
  <visual><global offwidth="1280" offheight="720"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" width="256" height="256" rgb1="0.85 0.85 0.85" rgb2="0.75 0.75 0.75"/>
    <material name="floor" texture="grid" texrepeat="{g.width:g} {g.room_size:g}"/>
    <material name="wall" rgba="0.35 0.35 0.45 1"/>
  </asset>
  <worldbody>
    <light pos="{cx} {cy} 12" dir="0 0 -1" directional="true"/>
    <camera name="top" pos="{cx} {cy} {max(g.width, g.room_size) * 1.1:.3f}" xyaxes="1 0 0 0 1 0"/>
    <geom name="floor" type="plane" material="floor" pos="{cx} {cy} 0" size="{cx} {cy} 0.1"/>
{walls_xml}
    <site name="goal" type="box" pos="{g.goal_x} {cy} 0.002" size="0.02 {cy} 0.002" rgba="0.1 0.8 0.2 0.8"/>
    <body name="robot" pos="0 0 0">
      <joint name="slide_x" type="slide" axis="1 0 0"/>
      <joint name="slide_y" type="slide" axis="0 1 0"/>
      <joint name="hinge_z" type="hinge" axis="0 0 1"/>
      <geom name="robot" type="cylinder" size="{r} 0.08" pos="0 0 0.08" rgba="0.9 0.4 0.1 1"/>
      <geom name="robot_heading" type="box" size="{r / 2} 0.015 0.01" pos="{r / 2} 0 0.17" rgba="0.1 0.1 0.1 1" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
</mujoco>
"""
