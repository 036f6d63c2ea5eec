"""Tests of envs_mjx/maze.py: geometry, collisions, traps, stages, rewards, observations, MJCF."""
from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from envs_mjx.maze import Maze, dead_end_is_low, maze_mjcf

R = 0.15  # robot radius (docs/design.md#environments-and-their-contract)
TOL = 1e-4  # allowed float error on clearances, m


class Compiled:
    """One env and its jitted functions, compiled once per module."""

    def __init__(self, env: Maze):
        self.env = env
        self.state_at = jax.jit(jax.vmap(env.state_at))
        self.reset = jax.jit(jax.vmap(env.reset))
        self.step = jax.jit(env.step)

        def rollout(state, actions):
            """Open-loop batch rollout: actions float32[T, B, 2] -> per-step stacked outputs."""
            def body(s, a):
                s = jax.vmap(env.step)(s, a)
                out = dict(pos=s.pipeline_state.pos, stage=s.info["stage"], rewards=s.info["rewards"],
                           reward=s.reward, done=s.done, success=s.metrics["success"],
                           truncation=s.info["truncation"])
                return s, out
            return jax.lax.scan(body, state, actions)[1]

        self.rollout = jax.jit(rollout)


@pytest.fixture(scope="module")
def mazes():
    cache: dict[tuple, Compiled] = {}

    def get(rooms: int, **kinematics) -> Compiled:
        key = (rooms, *sorted(kinematics.items()))
        if key not in cache:
            cache[key] = Compiled(Maze(rooms=rooms, **kinematics))
        return cache[key]

    return get


# ---------------------------------------------------------------- numpy geometry helpers

def point_segment_dist(p: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Distance of points p [..., 2] to every segment: [..., S]."""
    a, b = walls[:, :2], walls[:, 2:]
    ab = b - a
    ap = p[..., None, :] - a
    t = np.clip(np.sum(ap * ab, -1) / np.sum(ab * ab, -1), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=-1)


def path_segment_dist(p: np.ndarray, q: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Distance between path segments p->q ([..., 2] each) and every wall segment: [..., S]."""
    p64, q64, w64 = p.astype(np.float64), q.astype(np.float64), walls.astype(np.float64)
    a, b = w64[:, :2], w64[:, 2:]

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    d = (q64 - p64)[..., None, :]
    e = b - a
    pa = a - p64[..., None, :]
    den = cross(d, e)
    ok = np.abs(den) > 1e-12
    safe = np.where(ok, den, 1.0)
    t, s = cross(pa, e) / safe, cross(pa, d) / safe
    crossing = ok & (t >= 0) & (t <= 1) & (s >= 0) & (s <= 1)
    # Otherwise the closest pair involves an endpoint of one of the two segments.
    ends = np.minimum(point_segment_dist(p64, w64), point_segment_dist(q64, w64))
    for c in (a, b):
        cp = c - p64[..., None, :]
        dd = np.sum(d * d, -1)
        tc = np.clip(np.sum(cp * d, -1) / np.maximum(dd, 1e-18), 0.0, 1.0)
        ends = np.minimum(ends, np.linalg.norm(cp - tc[..., None] * d, axis=-1))
    return np.where(crossing, 0.0, ends)


def free_points(walls: np.ndarray, width: float, pts: np.ndarray, clearance: float) -> np.ndarray:
    """The points of pts [M, 2] inside the maze and at least `clearance` from every wall."""
    inside = (pts[:, 0] > 0) & (pts[:, 0] < width) & (pts[:, 1] > 0) & (pts[:, 1] < 5)
    clear = point_segment_dist(pts, walls).min(-1) >= clearance
    return pts[inside & clear]


def good_door_y(k: int) -> float:
    """Centre y of the door of inner wall k that does not lead into its pocket."""
    return 3.5 if dead_end_is_low(k) else 1.5


# ---------------------------------------------------------------- construction and layout

def test_constructor_validates_fields():
    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises(ValueError, match="rooms"):
            Maze(rooms=bad)
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="episode_length"):
            Maze(rooms=2, episode_length=bad)
    with pytest.raises(ValueError, match="wall_k"):
        dead_end_is_low(0)


def test_properties_and_two_room_layout():
    env = Maze(rooms=2)
    assert (env.num_stages, env.observation_size, env.action_size, env.backend) == (2, 24, 2, "jax")
    g = env.geometry
    assert (g.room_size, g.robot_radius, g.v_max, g.w_max, g.dt, g.n_beams, g.beam_range) == (5.0, 0.15, 1.0, 2.0, 0.2, 20, 3.0)
    assert g.doors == ((1.0, 2.0), (3.0, 4.0))
    assert g.goal_x == pytest.approx(9.7)
    assert [dead_end_is_low(k) for k in (1, 2, 3)] == [True, False, True]
    expected = {
        (0, 0, 10, 0), (10, 0, 10, 5), (10, 5, 0, 5), (0, 5, 0, 0),  # outer
        (5, 0, 5, 1), (5, 2, 5, 3), (5, 4, 5, 5),  # inner wall 1, doors [1, 2] and [3, 4]
        (5, 2.5, 7, 2.5), (7, 0, 7, 2.5),  # low pocket behind wall 1
    }
    assert env.walls.dtype == np.float32
    assert {tuple(float(v) for v in w) for w in env.walls} == {tuple(map(float, w)) for w in expected}
    # The high pocket of an even wall, mirrored.
    walls3 = {tuple(float(v) for v in w) for w in Maze(rooms=3).walls}
    assert {(10.0, 2.5, 12.0, 2.5), (12.0, 2.5, 12.0, 5.0)} <= walls3
    assert len(walls3) == 14


# ---------------------------------------------------------------- collisions

@pytest.mark.parametrize("slide", [False, True])
def test_walls_block_at_full_speed_from_every_heading(mazes, slide):
    c = mazes(3, reverse=True, slide=slide)  # both a low and a high pocket; reversing drives into walls behind too
    walls = c.env.walls
    # Starts 0.3 m either side of points along every wall, and around every wall end.
    a, b = walls[:, :2].astype(np.float64), walls[:, 2:].astype(np.float64)
    u = (b - a) / np.linalg.norm(b - a, axis=-1, keepdims=True)
    n = np.stack([-u[:, 1], u[:, 0]], -1)
    along = np.concatenate([a + f * (b - a) for f in (0.1, 0.5, 0.9)])
    normals = np.concatenate([n] * 3)
    ring = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], -1)
    ends = (np.concatenate([a, b])[:, None, :] + 0.3 * ring).reshape(-1, 2)
    pts = np.concatenate([along + 0.3 * normals, along - 0.3 * normals, ends])
    pts = np.unique(np.round(free_points(walls, 15.0, pts, R + 0.01), 4), axis=0)
    headings = np.arange(36) * 2 * np.pi / 36
    commands = np.array([[1.0, 0.0], [-1.0, 0.0], [1.0, 0.5]], np.float32)  # forward, reverse, arc
    P, H, C = np.meshgrid(np.arange(len(pts)), np.arange(36), np.arange(3), indexing="ij")
    P, H, C = P.ravel(), H.ravel(), C.ravel()
    start = c.state_at(jnp.asarray(pts[P], jnp.float32), jnp.asarray(headings[H], jnp.float32))
    T = 15  # 3 m at full speed, far more than the 0.3 m to the wall
    actions = jnp.broadcast_to(jnp.asarray(commands[C]), (T, len(P), 2))
    pos = np.asarray(c.rollout(start, actions)["pos"])  # [T, B, 2]
    path = np.concatenate([pts[P][None], pos], 0)
    # Every step's swept path stays at least one radius from every wall: no crossing, no overlap.
    clearance = path_segment_dist(path[:-1], path[1:], walls).min(-1)
    assert clearance.min() >= R - TOL, f"min clearance {clearance.min():.5f}"
    # Not vacuous: most robots driving straight end pressed against a wall.
    final = point_segment_dist(pos[-1], walls).min(-1)
    straight = C < 2
    assert np.mean(final[straight] < R + 0.01) > 0.5
    assert np.all(pos[..., 0] > R - TOL) and np.all(pos[..., 0] < 15 - R + TOL)
    assert np.all(pos[..., 1] > R - TOL) and np.all(pos[..., 1] < 5 - R + TOL)


# ---------------------------------------------------------------- task structure

def waypoints(rooms: int) -> np.ndarray:
    """Waypoints from the start through the good door of every inner wall to past the goal."""
    wps = []
    for k in range(1, rooms):
        y = good_door_y(k)
        wps += [(5 * k - 0.7, y), (5 * k + 0.5, y), (5 * k + 2.5, y)]  # through, then clear of pocket k
    wps.append((5 * rooms + 1.0, 2.5))
    return np.asarray(wps, np.float32)


@pytest.mark.parametrize("rooms", [2, 3, 4])
def test_scripted_controller_through_good_doors_reaches_goal(mazes, rooms):
    c = mazes(rooms)
    env, wps = c.env, jnp.asarray(waypoints(rooms))

    def act(pose, idx):
        reached = jnp.linalg.norm(wps[idx] - pose.pos) < 0.35
        idx = jnp.where(reached, jnp.minimum(idx + 1, len(wps) - 1), idx)
        d = wps[idx] - pose.pos
        err = jnp.mod(jnp.arctan2(d[1], d[0]) - pose.heading + jnp.pi, 2 * jnp.pi) - jnp.pi
        return jnp.stack([jnp.clip(jnp.cos(err), 0.0, 1.0) ** 2, jnp.clip(2.0 * err, -1.0, 1.0)]), idx

    @jax.jit
    def run(keys):
        def episode(key):
            def body(carry, _):
                s, idx = carry
                a, idx = act(s.pipeline_state, idx)
                s = env.step(s, a)
                return (s, idx), (s.metrics["success"], s.done, s.info["truncation"], s.info["rewards"], s.reward,
                                  s.metrics["pocket"])
            return jax.lax.scan(body, (env.reset(key), jnp.int32(0)), None, length=1000)[1]
        return jax.vmap(episode)(keys)

    success, done, trunc, rewards, reward, pocket = map(np.asarray, run(jax.random.split(jax.random.PRNGKey(rooms), 8)))
    assert success.any(axis=1).all(), "some episode never reached the goal"
    assert not pocket.any(), "the good doors never lead into a pocket"
    first = success.argmax(axis=1)  # < 1000 steps since the scan has 1000
    i = np.arange(len(first))
    assert np.all(done[i, first] == 1) and np.all(trunc[i, first] == 0)
    np.testing.assert_array_equal(rewards[i, first], np.ones((len(first), rooms), np.float32))
    np.testing.assert_allclose(reward[i, first], rooms)
    assert np.all(done[i, first - 1] == 0), "done before success"


@pytest.mark.parametrize("rooms", [2, 3, 4])
def test_greedy_straight_path_ends_in_next_pocket(mazes, rooms):
    """Driving straight right from a room's entry leads into the next wall's pocket and stops
    at its far side; only the last room's straight path reaches the goal."""
    c = mazes(rooms)
    offsets = (-0.25, 0.0, 0.25)
    entries = [(0.75, 1.5 + o) for o in offsets]  # the start area
    entries += [(5 * k + 0.5, good_door_y(k) + o) for k in range(1, rooms) for o in offsets]
    room_of = np.repeat(np.arange(rooms), len(offsets))
    start = c.state_at(jnp.asarray(entries, jnp.float32), jnp.zeros(len(entries), jnp.float32))
    out = c.rollout(start, jnp.broadcast_to(jnp.array([1.0, 0.0]), (60, len(entries), 2)))
    pos, success = np.asarray(out["pos"]), np.asarray(out["success"])
    for j, k in enumerate(room_of):
        if k == rooms - 1:
            assert success[:, j].any(), f"last room entry {entries[j]} did not reach the goal"
            continue
        x_next = 5.0 * (k + 1)
        assert pos[:, j, 0].max() <= x_next + 2.0 - R + TOL, "passed the pocket's far wall"
        x, y = pos[-1, j]
        assert x == pytest.approx(x_next + 2.0 - R, abs=0.01), f"entry {entries[j]} stopped at x={x}"
        assert (y < 2.5) if dead_end_is_low(k + 1) else (y > 2.5), f"entry {entries[j]} not in pocket (y={y})"
        assert float(c.env.in_pocket(jnp.asarray(pos[-1, j]))) == 1.0, "the pocket metric misses it"
        assert not success[:, j].any()


def test_pocket_metric_at_hand_picked_positions(mazes):
    env = mazes(4).env
    inside = [(6.0, 1.0), (5.2, 2.3), (11.0, 4.0), (16.5, 0.5)]  # wall 1 low, wall 2 high, wall 3 low
    outside = [(4.0, 1.0), (6.0, 3.5), (8.0, 1.0), (11.0, 1.0), (16.5, 4.0), (1.0, 1.0), (19.5, 1.0)]
    np.testing.assert_array_equal(np.asarray(env.in_pocket(jnp.asarray(inside + outside))),
                                  [1.0] * len(inside) + [0.0] * len(outside))
    start = env.state_at(jnp.array([6.0, 1.0]), jnp.float32(0.0))
    assert float(start.metrics["pocket"]) == 1.0 and float(env.step(start, jnp.zeros(2)).metrics["pocket"]) == 1.0


def test_stage_monotone_and_rewards_follow_definition(mazes):
    c = mazes(3)
    rng = np.random.default_rng(0)
    pts = free_points(c.env.walls, 15.0, rng.uniform([0, 0], [15, 5], (2000, 2)), R + 0.01)[:256]
    start = c.state_at(jnp.asarray(pts, jnp.float32), jnp.asarray(rng.uniform(-np.pi, np.pi, len(pts)), jnp.float32))
    # Smooth random actions (a random walk clipped to the box) so robots travel.
    actions = np.clip(np.cumsum(rng.normal(0, 0.4, (60, len(pts), 2)), 0), -1, 1).astype(np.float32)
    out = {k: np.asarray(v) for k, v in c.rollout(start, jnp.asarray(actions)).items()}
    stage0 = np.clip(np.floor(pts[:, 0] / 5), 0, 2).astype(np.int32)
    stages = np.concatenate([stage0[None], out["stage"]])
    assert out["stage"].dtype == np.int32
    assert np.all(np.diff(stages, axis=0) >= 0)
    rooms_seen = np.maximum.accumulate(np.clip(np.floor(out["pos"][..., 0] / 5), 0, 2), axis=0)
    np.testing.assert_array_equal(out["stage"], np.maximum(stage0, rooms_seen))
    assert (out["stage"][-1] > stage0).any(), "no robot changed stage: test is vacuous"
    r = out["rewards"]
    assert r.min() >= 0.0 and r.max() <= 1.0
    np.testing.assert_allclose(out["reward"], r.sum(-1), rtol=1e-6)
    n = np.arange(3)
    x = out["pos"][..., 0, None]
    expect = np.where(n < out["stage"][..., None], 1.0,
                      np.where(n == out["stage"][..., None], np.clip((x - 5 * n) / 5, 0, 1), 0.0))
    expect = np.where(out["success"][..., None] == 1, 1.0, expect)
    np.testing.assert_allclose(r, expect, atol=1e-6)


def test_rewards_at_hand_picked_states(mazes):
    c = mazes(3)
    env, step = c.env, c.step

    def at(x, y, heading=0.0):
        return env.state_at(jnp.array([x, y], jnp.float32), jnp.float32(heading))

    s = at(2.0, 2.5)
    assert int(s.info["stage"]) == 0
    np.testing.assert_allclose(s.info["rewards"], [0.4, 0.0, 0.0], atol=1e-6)
    s = at(7.5, 3.5)
    assert int(s.info["stage"]) == 1
    np.testing.assert_allclose(s.info["rewards"], [1.0, 0.5, 0.0], atol=1e-6)
    assert float(s.reward) == pytest.approx(1.5)
    # Back into room 0 from stage 1: stage stays 1, R_1 clips to 0, R_0 stays 1.
    s = at(5.3, 3.5, math.pi)
    for _ in range(5):
        s = step(s, jnp.array([1.0, 0.0]))
    assert float(s.pipeline_state.pos[0]) == pytest.approx(4.3, abs=1e-4)
    assert int(s.info["stage"]) == 1
    np.testing.assert_allclose(s.info["rewards"], [1.0, 0.0, 0.0], atol=1e-6)
    # Last room, short of the goal (9.7 + ...): x = 14.3 + 0.2 = 14.5 < 14.7.
    s = step(at(14.3, 2.5), jnp.array([1.0, 0.0]))
    np.testing.assert_allclose(s.info["rewards"], [1.0, 1.0, 0.9], atol=1e-5)
    assert float(s.done) == 0.0 and float(s.metrics["success"]) == 0.0
    # Crossing the goal line: every subtask reward is 1, the episode ends by success.
    s = step(s, jnp.array([1.0, 0.0]))
    np.testing.assert_array_equal(s.info["rewards"], [1.0, 1.0, 1.0])
    assert float(s.reward) == 3.0
    assert (float(s.done), float(s.metrics["success"]), float(s.info["truncation"])) == (1.0, 1.0, 0.0)


def test_kinematics_of_one_free_step(mazes):
    """reverse=True: heading turns by w dt; the centre moves v dt along the mid-step heading; actions clip."""
    c = mazes(2, reverse=True)
    s = c.env.state_at(jnp.array([2.5, 2.5]), jnp.float32(0.3))
    for action, v, w in (([1.0, 1.0], 1.0, 2.0), ([2.0, -3.0], 1.0, -2.0), ([-0.5, 0.25], -0.5, 0.5)):
        nxt = c.step(s, jnp.array(action, jnp.float32))
        mid = 0.3 + 0.5 * w * 0.2
        np.testing.assert_allclose(nxt.pipeline_state.pos, [2.5 + 0.2 * v * math.cos(mid), 2.5 + 0.2 * v * math.sin(mid)], atol=1e-6)
        assert float(nxt.pipeline_state.heading) == pytest.approx(0.3 + w * 0.2, abs=1e-6)
        np.testing.assert_allclose(nxt.obs[22:], [math.cos(0.3 + w * 0.2), math.sin(0.3 + w * 0.2)], atol=1e-6)
    # Headings wrap to [-pi, pi).
    turned = c.step(c.env.state_at(jnp.array([2.5, 2.5]), jnp.float32(3.0)), jnp.array([0.0, 1.0]))
    assert float(turned.pipeline_state.heading) == pytest.approx(3.4 - 2 * math.pi, abs=1e-6)


def test_forward_only_kinematics(mazes):
    """reverse=False: v = (a[0] + 1)/2 v_max, so a[0] = -1 stands still and 0 drives at half speed."""
    c = mazes(2, reverse=False)
    s = c.env.state_at(jnp.array([2.5, 2.5]), jnp.float32(0.3))
    for a0, v in ((-1.0, 0.0), (0.0, 0.5), (1.0, 1.0), (-3.0, 0.0)):
        nxt = c.step(s, jnp.array([a0, 0.0], jnp.float32))
        np.testing.assert_allclose(nxt.pipeline_state.pos, [2.5 + 0.2 * v * math.cos(0.3), 2.5 + 0.2 * v * math.sin(0.3)],
                                   atol=1e-6)


def test_blocked_step_slides_along_the_wall(mazes):
    """slide=True: a step into the wall x = 5 at 45 degrees keeps its component along the wall (False: stops)."""
    start, heading = jnp.array([4.75, 0.5]), jnp.float32(math.pi / 4)
    stopping, sliding = mazes(2, slide=False), mazes(2, slide=True)
    stop = stopping.step(stopping.env.state_at(start, heading), jnp.array([1.0, 0.0])).pipeline_state.pos
    slid = sliding.step(sliding.env.state_at(start, heading), jnp.array([1.0, 0.0])).pipeline_state.pos
    # Contact after 0.1 m in x (the centre reaches 5 - R = 4.85), i.e. a 0.1 sqrt(2) m chord of the step's 0.2 m.
    np.testing.assert_allclose(stop, [4.85, 0.6], atol=2e-3)
    # The remaining (0.2 - 0.1 sqrt(2)) m of chord, less its x part, moves up the wall.
    rest_y = (0.2 - 0.1 * math.sqrt(2)) / math.sqrt(2)
    np.testing.assert_allclose(slid, [4.85, 0.6 + rest_y], atol=2e-3)
    # Head-on there is nothing along the wall to keep.
    head_on = sliding.step(sliding.env.state_at(start, jnp.float32(0.0)), jnp.array([1.0, 0.0]))
    np.testing.assert_allclose(head_on.pipeline_state.pos, [4.85, 0.5], atol=2e-3)


def test_truncation_at_episode_length():
    env = Maze(rooms=2, episode_length=5)
    step = jax.jit(env.step)
    s = env.reset(jax.random.PRNGKey(0))
    for t in range(1, 6):
        s = step(s, jnp.zeros(2))
        assert int(s.info["steps"]) == t
        assert float(s.done) == (1.0 if t == 5 else 0.0)
    assert (float(s.info["truncation"]), float(s.metrics["success"])) == (1.0, 0.0)
    # Success on the last allowed step is a termination, not a truncation.
    short = Maze(rooms=2, episode_length=1)
    s = short.step(short.state_at(jnp.array([9.55, 2.5]), jnp.float32(0.0)), jnp.array([1.0, 0.0]))
    assert (float(s.done), float(s.info["truncation"]), float(s.metrics["success"])) == (1.0, 0.0, 1.0)


# ---------------------------------------------------------------- observations

def test_laser_beams_hand_computed(mazes):
    c = mazes(2)
    poses = jnp.array([[4.0, 4.2], [4.5, 1.5], [4.5, 1.5]], jnp.float32)
    headings = jnp.array([0.0, 0.0, math.pi / 2], jnp.float32)
    obs = np.asarray(c.state_at(poses, headings).obs)
    deg = math.radians
    # Near wall 1's top piece (x = 5, y in [4, 5]): ahead 1 m; 18 and 36 degrees hit the
    # same piece at 1/cos; up, the outer wall 0.8 m away; behind, out of range.
    np.testing.assert_allclose(obs[0, [0, 1, 2, 5, 10]],
                               np.array([1.0, 1 / math.cos(deg(18)), 1 / math.cos(deg(36)), 0.8, 3.0]) / 3, atol=1e-5)
    # In front of the low (dead-end) door: ahead through it to the pocket's far wall at x = 7;
    # 18 degrees also through the door, hitting x = 7 at y = 1.5 + 2.5 tan 18 < 2.5; floor 1.5 m below.
    expect = {0: 2.5 / 3, 1: 2.5 / math.cos(deg(18)) / 3, 5: 1.0, 10: 1.0, 15: 0.5}
    np.testing.assert_allclose(obs[1, list(expect)], list(expect.values()), atol=1e-5)
    # Same place facing up: beams are relative to the heading.
    expect = {0: 1.0, 5: 1.0, 10: 0.5, 15: 2.5 / 3}
    np.testing.assert_allclose(obs[2, list(expect)], list(expect.values()), atol=1e-5)
    np.testing.assert_allclose(obs[2, 20:], [0.45, 0.3, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(obs[0, 20:], [0.4, 0.84, 1.0, 0.0], atol=1e-6)


def test_jit_vmap_1024_shapes_and_dtypes(mazes):
    c = mazes(3)
    env, B = c.env, 1024

    @jax.jit
    def run(key):
        k0, k1 = jax.random.split(key)
        s0 = jax.vmap(env.reset)(jax.random.split(k0, B))
        s = s0
        for k in jax.random.split(k1, 3):
            s = jax.vmap(env.step)(s, jax.random.uniform(k, (B, 2), minval=-1.0, maxval=1.0))
        return s0, s

    s0, s = run(jax.random.PRNGKey(0))
    # reset and step agree on every leaf's shape and dtype, so lax.scan can carry the state.
    chex.assert_trees_all_equal_shapes_and_dtypes(s0, s)
    chex.assert_shape(s.obs, (B, 24))
    chex.assert_type([s.obs, s.reward, s.done, s.metrics["success"], s.metrics["pocket"], s.info["rewards"],
                      s.info["truncation"]], jnp.float32)
    chex.assert_type([s.info["stage"], s.info["steps"]], jnp.int32)
    chex.assert_shape([s.reward, s.done, s.info["stage"], s.info["truncation"], s.info["steps"], s.metrics["success"],
                       s.metrics["pocket"]], (B,))
    chex.assert_shape(s.info["rewards"], (B, 3))
    chex.assert_shape([s.pipeline_state.pos, s.pipeline_state.heading], [(B, 2), (B,)])
    chex.assert_tree_all_finite([s0.obs, s.obs])
    assert set(s.info) == {"stage", "rewards", "truncation", "steps"} and set(s.metrics) == {"success", "pocket"}
    pos, heading = np.asarray(s0.pipeline_state.pos), np.asarray(s0.pipeline_state.heading)
    assert pos[:, 0].min() >= 0.5 and pos[:, 0].max() <= 1.0 and pos[:, 0].std() > 0.1
    assert pos[:, 1].min() >= 1.25 and pos[:, 1].max() <= 1.75
    assert np.abs(heading).max() <= math.pi / 4 + 1e-6
    obs = np.asarray(s.obs)
    assert obs[:, :20].min() >= 0.0 and obs[:, :20].max() <= 1.0
    np.testing.assert_array_equal(np.asarray(s.info["steps"]), 3)


# ---------------------------------------------------------------- MJCF

@pytest.mark.parametrize("rooms", [2, 3, 4])
def test_mjcf_loads_with_the_same_layout(rooms):
    model = mujoco.MjModel.from_xml_string(maze_mjcf(rooms))
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(model.ngeom)]
    wall_ids = [i for i, nm in enumerate(names) if nm and nm.startswith("wall_")]
    walls = Maze(rooms=rooms).walls
    assert len(wall_ids) == len(walls) == 4 + 5 * (rooms - 1)
    data = mujoco.MjData(model)
    assert model.nq == 3
    pose = Maze(rooms=rooms).state_at(jnp.array([3.0, 2.0]), jnp.float32(0.7)).pipeline_state
    data.qpos[:] = np.asarray(pose.qpos())
    mujoco.mj_forward(model, data)
    np.testing.assert_allclose(data.geom_xpos[wall_ids, :2], (walls[:, :2] + walls[:, 2:]) / 2, atol=1e-4)
    np.testing.assert_allclose(data.geom("robot").xpos[:2], [3.0, 2.0], atol=1e-6)
    # The heading marker sits ahead of the centre along the heading.
    ahead = data.geom("robot_heading").xpos[:2] - data.geom("robot").xpos[:2]
    np.testing.assert_allclose(ahead / np.linalg.norm(ahead), [math.cos(0.7), math.sin(0.7)], atol=1e-6)
    assert data.site("goal").xpos[0] == pytest.approx(5 * rooms - 0.3)
