"""Reward terms of path tracking (paper 000 §III-D; docs/method.md §2), each in [0, 1].

Pure JAX, elementwise over any leading batch shape. The environment combines them as
``alpha * R_l + w_max * R_d(d_max) + w_mean * R_d(d_mean) + task terms`` (see
:class:`RewardWeights`). Lengths are joint-space arc lengths [rad]; deviations are the
weighted joint-space norms of :func:`weighted_deviation` [rad].
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

Array = jax.Array


def quadratic_decrease(x: Array, x_max) -> Array:
    """``(1 - min(1, x / x_max))**2``: 1 at ``x <= 0``, 0 at ``x >= x_max`` (the shape of every
    "stay close" term of the papers)."""
    rel = jnp.clip(x / x_max, 0.0, 1.0)
    return jnp.square(1.0 - rel)


def distance_reward(length: Array, length_state: Array, length_over) -> Array:
    """Path-length reward R_l (docs/method.md §2.2).

    ``length``: arc length commanded in this step (l); ``length_state``: reference length covered
    by the observed knots ahead of the current position (l_State); ``length_over``: the overshoot
    scale L_over = N * max_dis_between_knots. Rising quadratic ``1 - (1 - l/l_State)**2`` up to
    ``l = l_State``, then falling ``(1 - min(1, (l - l_State)/L_over))**2``. With ``l_State = 0``
    (path finished) only the falling branch applies.
    """
    safe_state = jnp.where(length_state > 0, length_state, 1.0)
    rising = 1.0 - jnp.square(1.0 - jnp.clip(length / safe_state, 0.0, 1.0))
    falling = quadratic_decrease(length - length_state, length_over)
    return jnp.where(length < length_state, rising, falling)


def deviation_reward(deviation: Array, threshold=0.25) -> Array:
    """Deviation reward R_d = ``(1 - min(1, d / threshold))**2`` (docs/method.md §2.3); d [rad]."""
    return quadratic_decrease(deviation, threshold)


def deviation_normalizer(weights: Array) -> Array:
    """``sqrt(n / sum(w**2))`` for per-joint deviation weights ``w`` [n] (docs/method.md §2.5), so that a
    deviation of the same size on every joint has the same weighted norm as without weights."""
    weights = jnp.asarray(weights, jnp.float32)
    return jnp.sqrt(weights.shape[-1] / jnp.sum(jnp.square(weights), axis=-1))


def weighted_deviation(q_ref: Array, q: Array, weights: Array | None = None) -> Array:
    """Per-sample deviation ``|| (q_ref - q) * w || * sqrt(n / sum w**2)`` [...]; ``q_ref, q`` [..., n]."""
    diff = q_ref - q
    if weights is None:
        return jnp.linalg.norm(diff, axis=-1)
    weights = jnp.asarray(weights, diff.dtype)
    return jnp.linalg.norm(diff * weights, axis=-1) * deviation_normalizer(weights)


def action_reward(action: Array, close_to_end: Array, peak: float = 1.0, start: float = 0.9) -> Array:
    """R_action (docs/method.md §2.4, iiwa random/target-point nets): rewards using the range fully.

    ``action`` [..., n] in [-1, 1]; m = max |action|: 0 for ``m <= start``, then
    ``max(0, 1 - ((m - peak)/(start - peak))**2)`` (1 at m = peak); 1 once the end knot is in the
    observation (``close_to_end`` [...] bool).
    """
    m = jnp.max(jnp.abs(action), axis=-1)
    value = jnp.maximum(0.0, 1.0 - jnp.square((m - peak) / (start - peak)))
    return jnp.where(close_to_end, 1.0, jnp.where(m > start, value, 0.0))


def jerk_reward(jerk_ratio: Array) -> Array:
    """R_jerk (not in the papers; docs/method.md §2.4): ``(1 - mean_j r_j)**2`` over the joints of
    the per-joint jerk ratios ``r = |a_1 - a_0| / (j_max dt)`` ``[..., n]`` in [0, 1] of one step
    (the acceleration change the action commands over the step, relative to the largest the jerk
    limit allows). 1 for a step that keeps every acceleration; 0 when every joint changes its
    acceleration at the jerk limit, as in bang-bang chatter (accelerations alternating between the
    ends of the safe range every step), which lengthens the executed path, and so earns R_l,
    without progress along the reference."""
    return quadratic_decrease(jnp.mean(jerk_ratio, axis=-1), 1.0)


#: the papers' Cartesian deviation threshold (``spline_cartesian_deviation_max_threshold``) [m]
CARTESIAN_THRESHOLD = 0.1


def cartesian_deviation_reward(deviation: Array, threshold=CARTESIAN_THRESHOLD) -> Array:
    """R_cart = ``(1 - min(1, d / threshold))**2`` (docs/method.md §2.4; not in the papers' released
    configs, whose Cartesian terms have weight 0): ``deviation`` [m], any shape, the distance of
    the executed target point from the reference's at equal arc length."""
    return quadratic_decrease(deviation, threshold)


#: normalisation of the ball position on the plate: half plate size minus 0.03 m [m]
BALL_HALF_RANGE = (0.5 * 0.3393 - 0.03, 0.5 * 0.2715 - 0.03)
#: offset of the ball reward (docs/method.md §2.4: a length used against normalised coordinates)
BALL_OFFSET = 0.06


def ball_reward(ball_xy: Array, half_range=BALL_HALF_RANGE, offset: float = BALL_OFFSET) -> Array:
    """R_ball (docs/method.md §2.4): ``clip((1 - max_i |rel_i|)/(1 - offset), 0, 1)**2`` while the ball
    is on the plate (all ``|rel_i| < 1``), else 0. ``ball_xy`` [..., 2]: ball position in the plate
    frame [m]; ``rel = ball_xy / half_range``.

    Deliberate difference: the published code omits ``abs`` (only +x/+y displacements lowered
    the reward, which looks like a bug); we use ``|rel|`` so the reward is symmetric."""
    rel = jnp.abs(ball_xy / jnp.asarray(half_range, jnp.float32))
    worst = jnp.max(rel, axis=-1)
    value = jnp.square(jnp.clip((1.0 - worst) / (1.0 - offset), 0.0, 1.0))
    return jnp.where(worst < 1.0, value, 0.0)


def tilt_angle(z_axis: Array) -> Array:
    """Angle [rad] between a body z-axis ``[..., 3]`` (world frame) and the world z-axis:
    ``pi/2 - arctan(z_z / ||z_xy||)``."""
    return jnp.pi / 2 - jnp.arctan2(z_axis[..., 2], jnp.linalg.norm(z_axis[..., :2], axis=-1))


def orientation_error(quat_wxyz: Array) -> Array:
    """``arccos(|q_w|) * 2 / pi`` in [0, 1] for a unit quaternion ``[..., 4]`` (w first)."""
    return jnp.arccos(jnp.clip(jnp.abs(quat_wxyz[..., 0]), 0.0, 1.0)) * 2.0 / jnp.pi


@dataclasses.dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (defaults: the papers' iiwa random-path network, docs/method.md §2.4).

    ``distance``: weight of the path-length reward R_l (the papers' alpha); ``max_deviation``/``mean_deviation``: R_d of d_max / d_mean;
    ``deviation_threshold`` [rad]; ``action``: R_action; ``ball``: R_ball; ``base_pos``,
    ``base_orn``, ``tilt``, ``end_point``: ARMAR-4 balance terms with their scales
    ``base_pos_max`` [m], ``base_orn_max`` [-], ``tilt_max`` [rad], ``end_point_max`` [m];
    ``jerk``: R_jerk (not in the papers; 0 in every papers' network).
    """

    distance: float = 2.0
    max_deviation: float = 0.9
    mean_deviation: float = 0.9
    deviation_threshold: float = 0.25
    action: float = 0.4
    ball: float = 0.0
    base_pos: float = 0.0
    base_orn: float = 0.0
    tilt: float = 0.0
    end_point: float = 0.0
    base_pos_max: float = 0.2
    base_orn_max: float = 0.5
    tilt_max: float = 0.125
    end_point_max: float = 0.4
    jerk: float = 0.0


def tracking_terms(weights: RewardWeights, length: Array, length_state: Array, length_over,
                   d_max: Array, d_mean: Array, action: Array, close_to_end: Array,
                   jerk_ratio: Array | None = None) -> dict[str, Array]:
    """Named, weighted path-tracking reward terms (sum them for the step reward); ``jerk_ratio``
    ``[..., n]``: the step's per-joint jerk ratios for R_jerk (:func:`jerk_reward`; ``None``: the
    term is 0)."""
    jerk = jnp.zeros(()) if jerk_ratio is None else weights.jerk * jerk_reward(jerk_ratio)
    return {
        "distance": weights.distance * distance_reward(length, length_state, length_over),
        "max_deviation": weights.max_deviation * deviation_reward(d_max, weights.deviation_threshold),
        "mean_deviation": weights.mean_deviation * deviation_reward(d_mean, weights.deviation_threshold),
        "action": weights.action * action_reward(action, close_to_end),
        "jerk": jerk,
    }


def balance_terms(weights: RewardWeights, base_pos: Array, base_quat: Array, base_z_axis: Array,
                  end_point_error: Array) -> dict[str, Array]:
    """Named, weighted humanoid balance terms (docs/method.md §2.4): ``base_pos`` [..., 3] [m] relative
    to the start, ``base_quat`` [..., 4] (w first), ``base_z_axis`` [..., 3], ``end_point_error``
    [...] mean Cartesian end-point distance [m]."""
    return {
        "base_pos": weights.base_pos * quadratic_decrease(jnp.linalg.norm(base_pos, axis=-1), weights.base_pos_max),
        "base_orn": weights.base_orn * quadratic_decrease(orientation_error(base_quat), weights.base_orn_max),
        "tilt": weights.tilt * quadratic_decrease(tilt_angle(base_z_axis), weights.tilt_max),
        "end_point": weights.end_point * quadratic_decrease(end_point_error, weights.end_point_max),
    }
