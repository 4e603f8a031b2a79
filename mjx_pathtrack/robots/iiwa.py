"""KUKA LBR iiwa 7 R800 kinematic limits as used by the papers (docs/limits.md §3, docs/robots.md §1).

Positions are the URDF limits minus the 0.035 rad safety buffer of the papers' robot scene;
velocities from the URDF; accelerations from the papers' code; jerk 2 a_max / dt by default.
"""

from __future__ import annotations

import numpy as np

from mjx_pathtrack.core.limits import JointLimits

JOINT_NAMES = tuple(f"iiwa_joint_{i}" for i in range(1, 8))
POS = np.array([2.93206, 2.0594, 2.93206, 2.0594, 2.93206, 2.0594, 3.01933])  # rad, symmetric
VEL = np.array([1.71042, 1.71042, 1.74533, 2.26893, 2.44346, 3.14159, 3.14159])  # rad/s
ACC = np.array([15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0])  # rad/s^2


def joint_limits(dt: float, jerk_factor: float = 1.0) -> JointLimits:
    """iiwa ``JointLimits`` with jerk ``jerk_factor * 2 * ACC / dt`` [rad/s^3]."""
    return JointLimits.from_acc(-POS, POS, VEL, ACC, dt, jerk_factor, names=JOINT_NAMES)
