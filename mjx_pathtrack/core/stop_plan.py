"""Static plan of the simulated stop ("tail") of the position bound, per joint and ``dt``.

Which joints can have their velocity floor bind during a stop (and so need the simulated tail),
and which sit in a position corridor so narrow that a hard stop's rebound could reach the
opposite limit (those plan a stop to near rest). Decided once from concrete limits with NumPy
(``None`` masks for traced limits). Used by :func:`mjx_pathtrack.core.limits.safe_acceleration_range_checked`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from mjx_pathtrack.core.joint_limits import JointLimits
from mjx_pathtrack.core.stopping import MARGIN, TAIL_VEL_MARGIN, _rise_loss


#: velocity floor of the stop in a narrow corridor, relative to the velocity limit (see _tail_plan)
REST_FACTOR = 0.02
#: a corridor counts as narrow below this multiple of the rebound bound (see _rebound_travel)
NARROW_FACTOR = 3.0


def _rebound_travel(A, J, V, dt, xp=np):
    """Upper bound [rad] of how far a joint that stopped with the acceleration at ``-A`` travels
    back before it can be at rest again (elementwise; ``xp`` = numpy or jax.numpy).

    The acceleration needs up to ``t_ramp = (ceil(A / (J dt)) + 1) dt`` to rise back to zero,
    losing ``v_lost <= min(V, _rise_loss(A))`` of velocity; braking that takes at most another
    ``t_ramp + v_lost / A``. The travel is bounded by ``v_lost`` times the whole time."""
    t_ramp = (xp.ceil(A / (J * dt)) + 1.0) * dt
    v_lost = xp.minimum(V, _rise_loss(A, J * dt, dt, xp))
    return v_lost * (2.0 * t_ramp + v_lost / A)


def _narrow(limits: JointLimits, dt, xp=np):
    """``[n]`` bool: joints whose position corridor is narrow against the rebound of a hard stop."""
    A, J, V = (xp.asarray(x) for x in (limits.acc, limits.jerk, limits.vel))
    span = xp.asarray(limits.pos_max) - xp.asarray(limits.pos_min)
    return xp.isfinite(span) & (span < NARROW_FACTOR * _rebound_travel(A, J, V, dt, xp))


class _TailPlan(NamedTuple):
    steps: int  # simulated decision steps around a stop (joints with a velocity-limit floor)
    rest_steps: int  # the same for joints in a narrow corridor (rest floor, longer stop)
    needs_tail: np.ndarray | None  # [n] bool: the velocity floor can bind (None: traced limits)
    narrow: np.ndarray | None  # [n] bool: narrow corridor, the stop comes to rest


def _tail_plan(limits: JointLimits, dt) -> _TailPlan:
    """Static plan of the velocity-safe tail of :func:`_safe_stop_peak`.

    ``steps`` decision steps around a stop are simulated, enough for the acceleration to swing
    from -A back to 0 (``A / (J dt)`` steps) plus margin. The velocity floor cannot bind when
    ``A dt + A^2/(2J) + J dt^2/8 <= V``: from a state with ``v >= 0`` and ``a >= -A`` the lowest
    next acceleration (``>= -A``) followed by the fastest settling rise loses at most ``A dt`` in
    that step and ``A^2/(2J) + J dt^2/8`` in the rise (the grid rise is never steeper than
    ``J``), so the velocity stays above ``-V``; those joints skip the tail.

    *Narrow corridors*: a stop that brakes as hard as possible ends with the acceleration near
    ``-A`` and rebounds; if the corridor is narrower than ``NARROW_FACTOR`` times the rebound
    bound (:func:`_rebound_travel`), the rebound could carry the joint into the opposite limit
    (found with random limits at dt = 0.4). Those joints plan a stop that comes to near rest
    instead (velocity floor ``REST_FACTOR * V``), simulated over ``rest_steps`` (the rise back to
    zero acceleration comes later). It is more cautious near the limits and costs a longer tail.

    For traced limits or ``dt`` the masks are ``None``: every joint simulates the longer tail
    with the narrow test evaluated in the trace, assuming a jerk limit down to ``A / dt``."""
    try:
        acc = np.asarray(limits.acc, np.float64)
        jerk = np.asarray(limits.jerk, np.float64)
        vel = np.asarray(limits.vel, np.float64)
        dt = float(dt)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return _TailPlan(5, 8, None, None)  # as for a jerk limit down to A / dt
    ratio = int(np.ceil(float(np.max(acc / (jerk * dt)))))
    j = jerk * (1.0 - 1e-4)  # the per-step budget is a hair below J dt (float32 reserve)
    drop = acc * dt + acc * acc / (2.0 * j) + j * dt * dt / 8.0
    needs_tail = drop * (1.0 + 1e-3) > vel * (1.0 - MARGIN) * (1.0 - TAIL_VEL_MARGIN)
    narrow = _narrow(limits, dt)
    return _TailPlan(ratio + 3, 2 * ratio + 6, needs_tail | narrow, narrow)
