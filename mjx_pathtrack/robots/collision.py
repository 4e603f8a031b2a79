"""Self-collision checks of joint configurations with MuJoCo's collision pipeline (offline, NumPy):
used to keep generated paths free of self-collision.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING

import mujoco
import numpy as np

if TYPE_CHECKING:
    from mjx_pathtrack.robots.registry import Robot


def in_collision(robot: Robot, q) -> np.ndarray:
    """Self-collision of joint configurations ``q [..., n]`` -> bool ``[...]``.

    Uses MuJoCo's collision detection on the robot's collision geoms with contacts between
    parent and child links excluded (MuJoCo's ``filterparent``) and, like an SRDF's
    disabled-collision list, body pairs that already touch at the initial pose ``q0``
    (neighbouring fitted primitives of the ARMAR meshes). Scene geoms (ball, plate, floor) are ignored.
    """
    robot._check_q(q)
    q = np.asarray(q, dtype=np.float64)
    model, excluded = _collision_model(robot)
    data = mujoco.MjData(model)
    flat = q.reshape(-1, robot.n_joints)
    out = np.zeros(len(flat), dtype=bool)
    for i, qi in enumerate(flat):
        data.qpos[:] = robot.qpos0
        data.qpos[robot.qpos_adr] = qi
        out[i] = bool(_colliding_pairs(model, data) - excluded)
    return out.reshape(q.shape[:-1])


def _collision_model(robot: Robot) -> tuple[mujoco.MjModel, frozenset]:
    if "collision" not in robot._cache:
        model = copy.deepcopy(robot.mj_model)
        model.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
        robot_geoms = model.geom_group == 3
        model.geom_contype[:] = np.where(robot_geoms, 1, 0)
        model.geom_conaffinity[:] = np.where(robot_geoms, 1, 0)
        # the broadphase also filters on the per-body OR of the geom bits (computed at compile time)
        for field in ("contype", "conaffinity"):
            per_body = np.zeros(model.nbody, dtype=np.int32)
            np.bitwise_or.at(per_body, model.geom_bodyid, getattr(model, f"geom_{field}"))
            getattr(model, f"body_{field}")[:] = per_body
        data = mujoco.MjData(model)
        data.qpos[:] = robot.qpos0
        robot._cache["collision"] = (model, frozenset(_colliding_pairs(model, data)))
    return robot._cache["collision"]


def _colliding_pairs(model: mujoco.MjModel, data: mujoco.MjData) -> set[tuple[int, int]]:
    mujoco.mj_kinematics(model, data)
    mujoco.mj_collision(model, data)
    pairs = set()
    for c in data.contact[: data.ncon]:
        if c.dist < 0:
            b1, b2 = model.geom_bodyid[c.geom1], model.geom_bodyid[c.geom2]
            pairs.add((min(b1, b2), max(b1, b2)))
    return pairs
