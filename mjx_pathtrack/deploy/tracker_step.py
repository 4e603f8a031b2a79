"""The online tracker's decision step in pure JAX (jitted once per tracker configuration by
:class:`~mjx_pathtrack.deploy.controller.OnlineTracker`, which only converts inputs and outputs):
the environment's transition with braking forced by a fault, the setpoints at the controller
instants, and the replacement of the reference ahead of the robot."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs.tracking import PathTrackingEnv, TrackState

Array = jax.Array

#: |v| <= STOP_FRACTION * vel and |a| <= STOP_FRACTION * acc of every joint count as stopped
STOP_FRACTION = 1e-6


class Core(NamedTuple):
    track: TrackState     # the environment's state (p, v, a, s, path, braking at the end, ...)
    fault: Array          # [] bool: brake regardless of the path (bad path/action, no path)


def step_core(env: PathTrackingEnv, controller_dt: float, core: Core, action: Array, bad_action: Array):
    """One decision step of the tracker (jitted per configuration): the environment's transition
    with braking forced by a fault, setpoints at the controller instants, status, next observation."""
    dt, k = env.config.dt, env.config.substeps
    track = core.track
    fault = core.fault | bad_action
    end_braking = track.braking
    action = jnp.where(fault, 0.0, action)
    new, _, _, _ = env.transition(track._replace(braking=end_braking | fault), action, fastest_stop=fault)
    length = new.path.length
    reached = env.end_reached(new.path, new.s)
    new = new._replace(braking=end_braking | reached)
    braking = end_braking | fault
    stopped = braking & at_rest(env.limits, new.v, new.a)
    # at rest after braking: remove the float32 residue (<= STOP_FRACTION of the limits) so
    # that the robot holds exactly (braking from v = a = 0 keeps v = a = 0)
    new = new._replace(v=jnp.where(stopped, 0.0, new.v), a=jnp.where(stopped, 0.0, new.a))
    t = controller_dt * jnp.arange(1, k + 1, dtype=jnp.float32)[:, None]
    p_set, v_set, a_set = L.integrate(track.p, track.v, track.a, new.a, dt, t)
    # the last setpoint is the next decision state exactly
    p_set, v_set, a_set = p_set.at[-1].set(new.p), v_set.at[-1].set(new.v), a_set.at[-1].set(new.a)
    jerk = (new.a - track.a) / dt
    obs = env.observe(new)
    return Core(new, fault), (p_set, v_set, a_set, jerk, new.s, length, reached, braking, stopped, obs)


def replace_core(track: TrackState, padded: Array, count: Array):
    """``update_path`` (jitted): drop the knots behind, replace the reference ahead of ``s``;
    returns the new state, the knot count and the count expected if nothing was dropped."""
    s = jnp.clip(track.s, 0.0, track.path.length)
    path, s = S.drop_behind(track.path, s)
    # replace_ahead keeps the knots up to the segment of s, then q(s), then the new knots
    seg, _ = S.locate(path, s)
    new_path = S.replace_ahead(path, s, padded, count)
    # knots dropped as duplicates of their predecessor (or of q(s)) are not lost capacity
    pts = jnp.concatenate([S.point_at(path, s)[None], padded])
    gap = jnp.linalg.norm(jnp.diff(pts, axis=0), axis=-1)
    distinct = jnp.sum((gap > S.DUPLICATE_DISTANCE) & (jnp.arange(padded.shape[0]) < count))
    expected = seg + 1 + 1 + distinct
    # the cut point q(s) is knot seg + 1 of the new reference: take its arc position (equal to
    # s up to rounding) so that the observation's knot0 is that point, as in the environment
    s = new_path.knot_s[seg + 1]
    track = track._replace(path=new_path, n_knots=new_path.n_knots, s=s, s_start=jnp.zeros(()),
                           braking=track.braking & (s >= new_path.length))
    return track, new_path.n_knots, expected


def at_rest(limits: L.JointLimits, v: Array, a: Array) -> Array:
    """``[]`` bool: every joint's |v| and |a| within ``STOP_FRACTION`` of its limits."""
    return jnp.all(jnp.abs(v) <= STOP_FRACTION * limits.vel) & jnp.all(jnp.abs(a) <= STOP_FRACTION * limits.acc)
