"""Pictures of env states, for videos: the drawing behind the envs' optional render hook.

The contract's render hook (docs/design.md#environments-and-their-contract) is an env method

    env.render_frames(states) -> np.uint8[T, H, W, 3]

where `states` is one episode's `State`s stacked along a leading time axis (host numpy leaves [T, ...]),
one RGB frame per state. The built-in envs implement it with this module:

* `mujoco_frames`: MuJoCo's offscreen renderer for a model and qpos [T, nq] (peg in hole, pusher, and any
  `StageWrapper` around a brax env with a MuJoCo model). It needs an OpenGL backend, which MuJoCo picks when
  `mujoco` is imported: set MUJOCO_GL=egl (or osmesa) before (docs/troubleshooting.md#videos-and-opengl).
* `maze_frames`: the maze drawn top-down with matplotlib, no OpenGL needed.

Nothing here chooses a GL backend at import.
"""
from __future__ import annotations

import os
import sys
from typing import Any

import numpy as np

GL_HELP = (
    "offscreen rendering needs an OpenGL backend chosen before `mujoco` is imported: "
    "MUJOCO_GL=egl (libEGL with a Mesa or NVIDIA driver) or MUJOCO_GL=osmesa (on Debian/Ubuntu: "
    "`apt-get install libosmesa6`; also PYOPENGL_PLATFORM=osmesa). Current MUJOCO_GL={!r}."
)


def mujoco_frames(model: Any, qpos: np.ndarray, camera: str | int = -1, height: int = 240,
                  width: int = 320) -> np.ndarray:
    """MuJoCo frames of `model` (a `mujoco.MjModel`) at each row of qpos float[T, nq]: uint8[T, height, width, 3].

    `camera`: a camera's name or id in the model, or -1 for MuJoCo's free camera. RuntimeError with what to set
    when no OpenGL context can be made (`GL_HELP`); ValueError for a frame larger than the model's offscreen
    buffer or qpos of the wrong shape.
    """
    import mujoco

    qpos = np.asarray(qpos)
    if qpos.ndim == 1:
        qpos = qpos[None]
    if qpos.ndim != 2 or qpos.shape[1] != model.nq:
        raise ValueError(f"expected qpos of shape [T, {model.nq}], got {qpos.shape} (pass one environment's states)")
    if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
        raise ValueError(f"frame {width}x{height} exceeds the model's offscreen buffer "
                         f"{model.vis.global_.offwidth}x{model.vis.global_.offheight}")
    chosen = getattr(mujoco, "GLContext", None)  # the backend picked when mujoco was imported
    if getattr(chosen, "__module__", "") == "mujoco.glfw" and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        # mujoco was imported before MUJOCO_GL was set and picked GLFW, which needs a display
        # (and a failed GLFW attempt leaves MuJoCo's GL state unusable): make an EGL context here.
        return _frames_own_context(model, qpos, camera, height, width, first_error="GLFW without a display")
    try:
        renderer = mujoco.Renderer(model, height=height, width=width)
    except Exception as err:  # noqa: BLE001 - the GL backend chosen when mujoco was imported failed
        raise RuntimeError(GL_HELP.format(os.environ.get("MUJOCO_GL")) + f" Cause: {err!r}") from err
    d = mujoco.MjData(model)
    frames = np.empty((qpos.shape[0], height, width, 3), np.uint8)
    try:
        for t, q in enumerate(qpos):
            d.qpos[:] = q
            mujoco.mj_forward(model, d)
            renderer.update_scene(d, camera=camera)
            frames[t] = renderer.render()
    finally:
        renderer.close()
    return frames


def _frames_own_context(model, qpos, camera, height, width, first_error):
    """`mujoco_frames` with an EGL (then OSMesa) context made here, for processes where `mujoco` was
    imported before MUJOCO_GL was set (its default, GLFW, needs a display)."""
    import mujoco

    errors = [f"MUJOCO_GL={os.environ.get('MUJOCO_GL')!r}: {first_error}"]
    for backend in ("egl", "osmesa"):
        try:
            if os.environ.get("PYOPENGL_PLATFORM", backend) != backend:
                raise RuntimeError(f"PYOPENGL_PLATFORM is {os.environ['PYOPENGL_PLATFORM']!r}")
            os.environ["PYOPENGL_PLATFORM"] = backend  # PyOpenGL reads it when first imported, below
            if backend == "egl":
                from mujoco.egl import GLContext
            else:
                from mujoco.osmesa import GLContext
            ctx = GLContext(width, height)
            ctx.make_current()
        except Exception as err:  # noqa: BLE001
            errors.append(f"{backend}: {err!r}")
            if os.environ.get("PYOPENGL_PLATFORM") == backend and "OpenGL" not in sys.modules:
                del os.environ["PYOPENGL_PLATFORM"]
            continue
        try:
            con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, con)
            scn, opt, cam = mujoco.MjvScene(model, maxgeom=2000), mujoco.MjvOption(), mujoco.MjvCamera()
            if camera == -1:
                mujoco.mjv_defaultFreeCamera(model, cam)
            else:
                cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
                cam.fixedcamid = model.camera(camera).id if isinstance(camera, str) else int(camera)
            rect = mujoco.MjrRect(0, 0, width, height)
            d = mujoco.MjData(model)
            rgb = np.empty((height, width, 3), np.uint8)
            frames = np.empty((qpos.shape[0], height, width, 3), np.uint8)
            for t, q in enumerate(qpos):
                d.qpos[:] = q
                mujoco.mj_forward(model, d)
                mujoco.mjv_updateScene(model, d, opt, None, cam, mujoco.mjtCatBit.mjCAT_ALL, scn)
                mujoco.mjr_render(rect, scn, con)
                mujoco.mjr_readPixels(rgb, None, rect, con)
                frames[t] = rgb[::-1]
            con.free()
            return frames
        finally:
            ctx.free()
    raise RuntimeError(GL_HELP.format(os.environ.get("MUJOCO_GL")) + " Tried: " + "; ".join(errors))


def maze_frames(maze: Any, states: Any, px_per_m: int = 48) -> np.ndarray:
    """Top-down frames of a maze episode (`envs_mjx.maze.Maze`; `states` stacked, leaves [T, ...]):
    uint8[T, H, W, 3] with H = 5·px_per_m + 80 and W = 5N·px_per_m + 96 (multiples of 16 at the default scale,
    as video encoders want).

    Walls, the goal line, the robot coloured by its stage (C0, C1, ...), its heading, path and laser rays (the
    observation's beams: obs[:n_beams] · beam range, beam i at heading + 2πi/n_beams). The top 48 pixels are left
    empty for a caption.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # local: only videos need matplotlib
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    g = maze.geometry
    pose = np.concatenate([np.asarray(states.pipeline_state.pos), np.asarray(states.pipeline_state.heading)[:, None]],
                          axis=-1)
    obs, stage = np.asarray(states.obs), np.asarray(states.info["stage"])
    width, height = int(g.width * px_per_m) + 96, int(g.room_size * px_per_m) + 80
    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    # A fixed axes box (no auto layout), so nothing shifts between frames.
    ax = fig.add_axes((48 / width, 32 / height, g.width * px_per_m / width, g.room_size * px_per_m / height))
    ax.set_xlim(0, g.width)
    ax.set_ylim(0, g.room_size)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    ax.add_collection(LineCollection(maze.walls.reshape(-1, 2, 2), colors="0.2", linewidths=2.5))
    ax.axvline(g.goal_x, color="tab:green", linestyle="--", linewidth=1.5)
    rays = ax.add_collection(LineCollection([], colors="tab:red", linewidths=0.6, alpha=0.6))
    path, = ax.plot([], [], color="tab:blue", linewidth=1, alpha=0.6)
    robot = ax.add_patch(Circle((0, 0), g.robot_radius, edgecolor="black", linewidth=0.8))
    heading, = ax.plot([], [], color="black", linewidth=1.5)

    offsets = 2 * np.pi * np.arange(g.n_beams) / g.n_beams
    frames = np.empty((len(pose), height, width, 3), np.uint8)
    for t in range(len(pose)):
        x, y, theta = pose[t]
        ends = obs[t, :g.n_beams, None] * g.beam_range * np.stack([np.cos(theta + offsets), np.sin(theta + offsets)],
                                                                   axis=-1)
        rays.set_segments(np.stack([np.broadcast_to((x, y), ends.shape), (x, y) + ends], axis=1))
        path.set_data(pose[:t + 1, 0], pose[:t + 1, 1])
        robot.center = (x, y)
        robot.set_facecolor(f"C{stage[t] % 10}")  # colour = the acting stage's agent
        heading.set_data([x, x + 2 * g.robot_radius * np.cos(theta)], [y, y + 2 * g.robot_radius * np.sin(theta)])
        canvas.draw()
        frames[t] = np.asarray(canvas.buffer_rgba())[..., :3]
    return frames
