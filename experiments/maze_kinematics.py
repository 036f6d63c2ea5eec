"""The 2-room maze with the robot kinematics the paper leaves open, as `--env` factories.

SPEC §4 fixes the geometry but says only "actions scaled to linear and angular
velocity". Our default lets a[0] < 0 drive backwards and stops a blocked step at
the wall. These factories train the same task with the other readings:

    cd experiments && python -m ccp_jax.train --env maze_kinematics:forward_2room ...

forward: v = (a[0] + 1)/2 v_max, so a zero-mean policy drives forwards at half speed;
slide: a blocked step slides along the wall it touched.
"""
from __future__ import annotations

from envs_mjx.maze import Maze


def forward_2room() -> Maze:
    return Maze(rooms=2, reverse=False)


def slide_2room() -> Maze:
    return Maze(rooms=2, slide=True)


def forward_slide_2room() -> Maze:
    return Maze(rooms=2, reverse=False, slide=True)
