"""Per-joint kinematic limits (position, velocity, acceleration, jerk) as a validated JAX pytree.

Units: rad, rad/s, rad/s^2, rad/s^3 (m, m/s, ... for prismatic joints). Re-exported by
:mod:`mjx_pathtrack.core.limits`, where the safe acceleration range built on them lives.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


@jax.tree_util.register_pytree_node_class
class JointLimits:
    """Per-joint kinematic limits, a pytree of float arrays ``[n]``.

    ``pos_min``/``pos_max`` [rad or m] (``-inf``/``+inf`` for a continuous joint); ``vel``,
    ``acc``, ``jerk`` are symmetric magnitudes [rad/s, rad/s^2, rad/s^3] (> 0).
    Construction from concrete values validates and raises ``ValueError`` naming the joint.
    """

    __slots__ = ("pos_min", "pos_max", "vel", "acc", "jerk")

    def __init__(self, pos_min, pos_max, vel, acc, jerk, names=None):
        fields = dict(pos_min=pos_min, pos_max=pos_max, vel=vel, acc=acc, jerk=jerk)
        if not any(isinstance(x, jax.core.Tracer) for x in fields.values()):
            _validate(fields, names)
        for key, value in fields.items():
            object.__setattr__(self, key, jnp.asarray(value, dtype=jnp.float32))

    def __setattr__(self, key, value):
        raise dataclasses.FrozenInstanceError(f"JointLimits is immutable (tried to set {key})")

    @classmethod
    def from_acc(cls, pos_min, pos_max, vel, acc, dt: float, jerk_factor: float = 1.0, names=None):
        """Limits with the papers' default jerk ``jerk_factor * 2 * acc / dt`` (docs/limits.md §3)."""
        acc = np.asarray(acc, dtype=np.float64)
        return cls(pos_min, pos_max, vel, acc, jerk_factor * 2.0 * acc / dt, names=names)

    @property
    def n_joints(self) -> int:
        return int(self.vel.shape[-1])

    @property
    def continuous(self) -> Array:
        """``[n]`` bool: joints without position limits."""
        return ~(jnp.isfinite(self.pos_min) & jnp.isfinite(self.pos_max))

    def tree_flatten(self):
        return (self.pos_min, self.pos_max, self.vel, self.acc, self.jerk), None

    @classmethod
    def tree_unflatten(cls, aux, children):
        obj = object.__new__(cls)
        for key, value in zip(cls.__slots__, children):
            object.__setattr__(obj, key, value)
        return obj

    def __repr__(self):
        return (f"JointLimits(n={self.n_joints}, pos_min={self.pos_min}, pos_max={self.pos_max}, "
                f"vel={self.vel}, acc={self.acc}, jerk={self.jerk})")


def _validate(fields: dict, names) -> None:
    arrays = {k: np.asarray(v, dtype=np.float64) for k, v in fields.items()}
    shapes = {k: a.shape for k, a in arrays.items()}
    if any(len(s) != 1 for s in shapes.values()) or len(set(shapes.values())) != 1:
        raise ValueError(f"JointLimits: all limits must be 1-D arrays of the same length [n], got {shapes}")
    n = shapes["vel"][0]
    if n == 0:
        raise ValueError("JointLimits: need at least one joint")
    if names is not None and len(names) != n:
        raise ValueError(f"JointLimits: {len(names)} names for {n} joints")

    def joint(i):
        return f"joint {i}" + (f" ({names[i]})" if names is not None else "")

    for key, a in arrays.items():
        bad = np.flatnonzero(np.isnan(a))
        if bad.size:
            raise ValueError(f"JointLimits: {key} of {joint(bad[0])} is NaN")
    lo, hi = arrays["pos_min"], arrays["pos_max"]
    bad = np.flatnonzero(np.isfinite(lo) != np.isfinite(hi))
    if bad.size:
        raise ValueError(f"JointLimits: {joint(bad[0])} has one infinite position limit "
                         f"({lo[bad[0]]}, {hi[bad[0]]}); use -inf and +inf together for a continuous joint")
    bad = np.flatnonzero(np.isfinite(lo) & (lo >= hi))
    if bad.size:
        raise ValueError(f"JointLimits: {joint(bad[0])} has pos_min >= pos_max ({lo[bad[0]]} >= {hi[bad[0]]})")
    for key in ("vel", "acc", "jerk"):
        a = arrays[key]
        bad = np.flatnonzero(~(a > 0) | ~np.isfinite(a))
        if bad.size:
            raise ValueError(f"JointLimits: {key} limit of {joint(bad[0])} must be finite and > 0, got {a[bad[0]]}")
