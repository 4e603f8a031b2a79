"""Action priors: actions computed from the observation that a policy's mean is added to.

A policy with a prior acts ``clip(prior(obs) + network(obs), -1, 1)`` (deterministic; PPO samples
around that mean): at a zero network output the prior acts alone. The prior has no parameters;
it is part of the policy network (:func:`mjx_pathtrack.deploy.networks.networks`), so training,
evaluation and the exported policy all include it, and the environment is unchanged.

:class:`HoldPrior` holds some joints still at their home position
(:func:`~mjx_pathtrack.core.limits.hold_action`, a critically damped spring mapped into the safe
range). ARMAR-4's legs (``train.py --task balance --legs controlled --leg-prior hold``): the
middle of the safe range (action 0) keeps a joint's *velocity*, so a policy whose legs start at a
zero action lets them drift and the robot falls; with the prior a zero action holds the legs
exactly, and the network learns only how to move them away from that.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import limits as L

Array = jax.Array

#: natural frequency [rad/s] of the hold: a joint off its home by e rad returns within about 1 s
HOLD_OMEGA = 5.0


class HoldPrior:
    """The actions ``[..., n]`` that hold the joints ``joints`` at ``home`` (0 on the others),
    read from a path-tracking observation ``[..., >= 3 n]`` whose first blocks are the position,
    velocity and acceleration of the ``n`` joints normalised by ``limits``
    (:meth:`~mjx_pathtrack.envs.tracking.PathTrackingEnv.observe`; later entries are ignored).

    ``limits``: the ``n`` action joints' limits; ``joints``: indices of the held joints (finite
    position limits); ``home`` ``[n]`` [rad]; ``dt`` [s]: the decision step; ``omega`` [rad/s]."""

    def __init__(self, limits: L.JointLimits, joints, home, dt: float, omega: float = HOLD_OMEGA):
        joints = np.asarray(joints, np.int64).reshape(-1)
        n = int(np.asarray(limits.vel).shape[-1])
        if joints.size == 0 or joints.min() < 0 or joints.max() >= n or len(set(joints.tolist())) != joints.size:
            raise ValueError(f"hold prior: joints {joints.tolist()} must be distinct indices into the {n} joints")
        lo, hi = (np.asarray(x, np.float64)[joints] for x in (limits.pos_min, limits.pos_max))
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("hold prior: a held joint has no finite position limits (a continuous joint)")
        home = np.asarray(home, np.float32).reshape(-1)
        if home.shape != (n,) or np.any(home[joints] < lo) or np.any(home[joints] > hi):
            raise ValueError(f"hold prior: home must be {n} positions within the held joints' limits")
        if not (np.isfinite(dt) and dt > 0 and np.isfinite(omega) and omega > 0):
            raise ValueError(f"hold prior: dt ({dt}) and omega ({omega}) must be > 0")
        self.n, self.joints, self.dt, self.omega = n, joints, float(dt), float(omega)
        self.limits = L.JointLimits(*(np.asarray(x)[joints] for x in (limits.pos_min, limits.pos_max, limits.vel,
                                                                       limits.acc, limits.jerk)))
        self.home = jnp.asarray(home[joints])

    def __call__(self, obs: Array) -> Array:
        """Hold actions ``[..., n]`` in [-1, 1] (0 on joints not held) of observations ``[..., obs]``."""
        n, idx, lim = self.n, self.joints, self.limits
        p = lim.pos_min + 0.5 * (obs[..., idx] + 1.0) * (lim.pos_max - lim.pos_min)  # tracking.normalize_position
        v = obs[..., n + idx] * lim.vel
        a = obs[..., 2 * n + idx] * lim.acc
        held = L.hold_action(lim, p, v, a, self.dt, self.home, self.omega)
        return jnp.zeros(obs.shape[:-1] + (n,), held.dtype).at[..., idx].set(held)
