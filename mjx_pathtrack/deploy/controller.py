"""Online path tracking for a real trajectory controller: stream knots in, setpoints out.

:class:`OnlineTracker` runs a trained policy (an :class:`~mjx_pathtrack.deploy.export.ExportedPolicy`
or any callable ``obs [obs_size] -> action [n]``) exactly as the environment does, one decision
step ``dt`` at a time, and returns the position / velocity / acceleration setpoints of the next
``dt`` at the controller rate (Ruckig-style explicit output object, :class:`TrackerOutput`)::

    tracker = OnlineTracker(load_policy("export/"), p0, controller_dt=1e-3)
    tracker.set_path(knots)                     # [K, n_path] joint-space knots
    while True:
        out = tracker.step()                    # out.position [k, n] at out.time [k], ...
        send_to_robot(out)                      # k = dt / controller_dt setpoints
        if new_knots_arrived:
            tracker.update_path(new_knots)      # replace the reference ahead of the robot
        if out.status is Status.STOPPED: ...

Safety does not depend on the policy: every action (clipped to [-1, 1]; NaN, inf or a wrong
shape count as a fault) is mapped into :func:`~mjx_pathtrack.core.limits.safe_acceleration_range`,
so position, velocity, acceleration and jerk limits hold at every instant (constant jerk inside
a step) and a safe continuation always exists. The tracker brakes
(:func:`~mjx_pathtrack.core.limits.braking_acceleration`) to a stop and then holds when

* the reference end was reached (as in the environment: from the step after reaching it),
* a bad path arrives (:meth:`OnlineTracker.set_path` / :meth:`update_path` raise
  :class:`PathError` and keep the previous reference: the held state is never touched),
* the policy returned an invalid action, or no path was set yet.

A later accepted ``set_path`` / ``update_path`` clears the fault; braking at the end stops as soon
as the reference goes on (:meth:`~mjx_pathtrack.envs.tracking.PathTrackingEnv.replace_reference`).

The per-step core (observation, safe range, integration, arc progress) is the environment's own
code (:meth:`PathTrackingEnv.observe`, :meth:`PathTrackingEnv.transition` with
``EnvConfig(adjustable=True)``) in one function jitted once per tracker; Python only converts the
inputs and outputs. Units: rad, rad/s, rad/s², rad/s³ (m for prismatic joints), s.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from types import SimpleNamespace
from typing import Callable, NoReturn

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.deploy.export import MANIFEST_ENV_SETTINGS, env_settings, manifest_knot_rule
from mjx_pathtrack.deploy.tracker_step import Core, at_rest, replace_core, step_core
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv, TrackState
from mjx_pathtrack.paths.datasets import DatasetError
from mjx_pathtrack.paths.user_paths import PreparedPath, into_limits, prepare_path
from mjx_pathtrack.robots.registry import POS_BUFFER

Array = jax.Array

#: default capacity of the held reference (knots from the one before the robot to the end):
#: every committed dataset path fits (the longest has 222 knots); the cost of a step grows
#: only slowly with it (a knot search over the padded array)
MAX_KNOTS = 256
#: a first knot of ``set_path`` this close [rad] to the current position replaces it
START_TOLERANCE = 1e-4
#: relative tolerance of ``controller_dt`` dividing ``dt``
RATE_TOLERANCE = 1e-9


class PathError(ValueError):
    """A rejected reference (wrong shape, NaN/inf, outside the position limits, too many knots)."""


class Status(str, enum.Enum):
    TRACKING = "tracking"   # following the policy
    BRAKING = "braking"     # fastest safe stop (end reached, fault or no path)
    STOPPED = "stopped"     # at rest after braking; holds until a new path is accepted


@dataclasses.dataclass(frozen=True)
class TrackerOutput:
    """Setpoints of the next decision step and the tracker's status after it.

    time ``[k]`` [s] since construction (the end of each controller period, the last one is
    the next decision instant); position, velocity, acceleration ``[k, n]``; jerk ``[n]``
    (constant within the step); status; s / path_length [rad] arc position on the reference
    and its length; progress = s / path_length; reached_end; fault: why the tracker brakes
    (``None`` when tracking or braking at the end); action ``[n]`` the policy output used
    (zeros when it was invalid; ignored while braking).
    """

    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray
    status: Status
    s: float
    path_length: float
    progress: float
    reached_end: bool
    fault: str | None
    action: np.ndarray


class OnlineTracker:
    """Policy-driven online path tracker (see the module docstring).

    policy: ``ExportedPolicy`` (limits, dt, n_next, path_joints, max_dis_between_knots taken from
    its manifest) or any callable ``obs [obs_size] -> action [n]`` (then ``limits``, ``dt``,
    ``n_next``, ``max_dis_between_knots`` are required; ``path_joints`` defaults to all,
    ``knots_frame`` to the papers' "absolute" observation); end_tolerance [rad]: brake to a stop
    once within this arc length of the path end (``EnvConfig.end_tolerance``; 0: at the end);
    end_braking: when braking at the end starts (``EnvConfig.end_braking``; from the manifest of
    an export, else "at_end"); end_stop: how the robot stops there (``EnvConfig.end_stop``; from
    the manifest, else "fastest"; ``end_knot_tolerance`` [rad] with it); a fault always brakes every
    joint as fast as it can;
    position ``[n]`` current joint positions, velocity / acceleration ``[n]`` (default 0);
    controller_dt [s]: setpoint period, must divide ``dt``; max_knots: capacity of the reference;
    knot_rule: where the policy's training paths have their knots (from the manifest of an
    export; for a plain callable default the papers' curvature rule capped at
    ``max_dis_between_knots``): every path given to :meth:`set_path` / :meth:`update_path` is
    re-knotted by it, so that the policy sees knots like its training knots whatever spacing
    the caller chose (:mod:`mjx_pathtrack.paths.user_paths`); ``keep_knots``: give the policy the
    knots as they come; limit_allowance [rad]: knots up to this far beyond the position limits
    (the robot's URDF limits lie :data:`~mjx_pathtrack.robots.registry.POS_BUFFER` outside the
    model's) are moved onto them, further ones are refused. :attr:`path_report` tells what was
    done to the last accepted path.
    Raises ``ValueError`` for inconsistent inputs or an unsafe initial state.
    """

    def __init__(self, policy: Callable, position, velocity=None, acceleration=None, *,
                 controller_dt: float, limits: L.JointLimits | None = None, dt: float | None = None,
                 n_next: int | None = None, max_dis_between_knots: float | None = None, path_joints=None,
                 max_knots: int = MAX_KNOTS, knots_frame: str | None = None, end_tolerance: float = 0.0,
                 end_braking: str | None = None, end_stop: str | None = None,
                 end_knot_tolerance: float | None = None, knot_rule: KnotRule | None = None, keep_knots: bool = False,
                 limit_allowance: float = POS_BUFFER):
        manifest = getattr(policy, "manifest", None)
        settings = dict(knots_frame=knots_frame, end_braking=end_braking, end_stop=end_stop,
                        end_knot_tolerance=end_knot_tolerance)
        if manifest is not None:
            lim = manifest["limits"]
            none_inf = lambda xs, sign: [sign * np.inf if x is None else x for x in xs]  # noqa: E731
            from_manifest = dict(
                limits=L.JointLimits(none_inf(lim["pos_min"], -1), none_inf(lim["pos_max"], 1), lim["vel"], lim["acc"],
                                     lim["jerk"], names=manifest.get("joint_names")),
                dt=manifest["dt"], n_next=manifest["n_next"], max_dis_between_knots=manifest["max_dis_between_knots"],
                path_joints=manifest["path_joints"])
            given = dict(limits=limits, dt=dt, n_next=n_next, max_dis_between_knots=max_dis_between_knots,
                         path_joints=path_joints, knot_rule=knot_rule, **settings)
            clash = [k for k, v in given.items() if v is not None]
            if clash:
                raise ValueError(f"{', '.join(clash)} come(s) from the export manifest; do not pass them")
            limits, dt, n_next = from_manifest["limits"], from_manifest["dt"], from_manifest["n_next"]
            max_dis_between_knots, path_joints = from_manifest["max_dis_between_knots"], from_manifest["path_joints"]
            settings = env_settings(manifest)
            knot_rule = manifest_knot_rule(manifest)
        else:  # a plain callable: the settings a manifest without them implies, unless given
            settings = {key: MANIFEST_ENV_SETTINGS[key] if value is None else value for key, value in settings.items()}
            settings = {key: value for key, value in settings.items() if value is not None}
        if not callable(policy):
            raise ValueError(f"policy must be callable obs -> action, got {type(policy).__name__}")
        missing = [k for k, v in dict(limits=limits, dt=dt, n_next=n_next,
                                      max_dis_between_knots=max_dis_between_knots).items() if v is None]
        if missing:
            raise ValueError(f"a plain callable policy needs {', '.join(missing)}")
        if not isinstance(limits, L.JointLimits):
            raise ValueError(f"limits must be a JointLimits, got {type(limits).__name__}")
        n = limits.n_joints
        dt = float(dt)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be > 0, got {dt}")
        controller_dt = float(controller_dt)
        if not (np.isfinite(controller_dt) and 0 < controller_dt <= dt):
            raise ValueError(f"controller_dt must be in (0, dt = {dt}], got {controller_dt}")
        k = int(round(dt / controller_dt))
        if abs(k * controller_dt - dt) > RATE_TOLERANCE * dt:
            raise ValueError(f"controller_dt = {controller_dt} s does not divide dt = {dt} s")
        if int(n_next) < 1:
            raise ValueError(f"n_next must be >= 1, got {n_next}")
        if int(max_knots) < 3:
            raise ValueError(f"max_knots must be >= 3, got {max_knots}")
        if not (np.isfinite(limit_allowance) and limit_allowance >= 0):
            raise ValueError(f"limit_allowance must be a finite number >= 0 [rad], got {limit_allowance}")
        if knot_rule is None:
            knot_rule = KnotRule(max_spacing=float(max_dis_between_knots))
        self.knot_rule: KnotRule | None = None if keep_knots else knot_rule
        self.limit_allowance = float(limit_allowance)
        self.path_report: PreparedPath | None = None
        self.policy, self.limits, self.dt, self.controller_dt, self.substeps = policy, limits, dt, controller_dt, k
        self.max_knots = int(max_knots)
        self.path_joints = np.arange(n) if path_joints is None else np.asarray(path_joints, np.int64)
        self.robot_name = None if manifest is None else manifest["robot"]
        if self.path_joints.ndim != 1 or len(self.path_joints) == 0 or len(set(self.path_joints.tolist())) != len(
                self.path_joints) or self.path_joints.min() < 0 or self.path_joints.max() >= n:
            raise ValueError(f"path_joints must be distinct joint indices in [0, {n}), got {path_joints}")
        state = [self._joint_vector(x, name) for x, name in
                 ((position, "position"), (velocity, "velocity"), (acceleration, "acceleration"))]
        p, v, a = state
        check = _checked_range(limits, p, v, a, dt)
        if bool(np.any(np.asarray(check.violation))):
            bad = int(np.flatnonzero(np.asarray(check.violation))[0])
            raise ValueError(f"initial state of joint {bad} (p={p[bad]:.6g}, v={v[bad]:.6g}, a={a[bad]:.6g}) "
                             f"is outside the limits or cannot be stopped safely")
        self._lo = np.asarray(limits.pos_min, np.float64)[self.path_joints]
        self._hi = np.asarray(limits.pos_max, np.float64)[self.path_joints]
        # the environment with a placeholder reference (it only fixes the shapes: the tracker's
        # state carries its own path, EnvConfig.adjustable)
        m = len(self.path_joints)
        here = np.asarray(p, np.float64)[self.path_joints]
        placeholder = S.make_path(np.stack([here, here + 1e-3]), self.max_knots)
        config = EnvConfig(dt=dt, n_next=int(n_next), substeps=k, deviation_samples=max(k, 1), terminate_deviation=None,
                           adjustable=True, end_tolerance=float(end_tolerance), **settings)
        self.env = PathTrackingEnv(limits, jax.tree.map(lambda x: x[None], placeholder), float(max_dis_between_knots),
                                   config, path_joints=self.path_joints)
        self.observation_size, self.n_joints, self.n_path = self.env.observation_size, n, m
        expected = getattr(policy, "observation_size", self.observation_size)
        if expected != self.observation_size:
            raise ValueError(f"policy expects observations of size {expected}, "
                             f"the tracker builds {self.observation_size}")
        track = TrackState(p=jnp.asarray(p), v=jnp.asarray(v), a=jnp.asarray(a), s=jnp.zeros(()),
                           s_start=jnp.zeros(()), path_index=jnp.zeros((), jnp.int32), n_knots=placeholder.n_knots,
                           steps=jnp.zeros((), jnp.int32), max_steps=jnp.asarray(np.iinfo(np.int32).max, jnp.int32),
                           braking=jnp.ones((), bool), rng=jax.random.PRNGKey(0), path=placeholder, executor=None)
        self._core = Core(track, jnp.ones((), bool))
        self._fault: str | None = "no path set"
        self._has_path = False
        self._time_steps = 0
        # one compilation per configuration (shared by trackers with equal settings)
        key = (tuple(np.asarray(x).tobytes() for x in jax.tree.leaves(limits)), config,
               float(max_dis_between_knots), tuple(self.path_joints.tolist()), self.max_knots)
        if key not in _COMPILED:
            _COMPILED[key] = (jax.jit(functools.partial(step_core, self.env, controller_dt)), jax.jit(replace_core),
                              jax.jit(self.env.observe))
        self._step_fn, self._replace_fn, self._obs_fn = _COMPILED[key]
        self._obs = self._obs_fn(track)
        self._last_status = Status.STOPPED if self._at_rest(v, a) else Status.BRAKING

    # -- state ------------------------------------------------------------------------------

    @property
    def position(self) -> np.ndarray:
        return np.asarray(self._core.track.p)

    @property
    def velocity(self) -> np.ndarray:
        return np.asarray(self._core.track.v)

    @property
    def acceleration(self) -> np.ndarray:
        return np.asarray(self._core.track.a)

    @property
    def s(self) -> float:
        return float(self._core.track.s)

    @property
    def path(self) -> S.Path:
        """The held reference (a fixed-size :class:`~mjx_pathtrack.core.spline.Path`)."""
        return self._core.track.path

    @property
    def time(self) -> float:
        return self._time_steps * self.dt

    @property
    def status(self) -> Status:
        return self._last_status

    @property
    def fault(self) -> str | None:
        return self._fault

    # -- reference --------------------------------------------------------------------------

    def set_path(self, knots) -> None:
        """Start a new reference ``knots [K, n_path]`` from the current position (robot at rest).

        The current position of the path joints becomes the first knot (a first knot within
        ``START_TOLERANCE`` of it is replaced by it). Raises :class:`PathError` for a bad path
        (the tracker then brakes and keeps its previous reference) and ``RuntimeError`` while the
        robot moves (use :meth:`update_path` then)."""
        if not self._at_rest(self.velocity, self.acceleration):
            raise RuntimeError("set_path needs the robot at rest; use update_path during motion")
        k = self._checked_knots(knots, "set_path")
        here = np.asarray(self.position, np.float64)[self.path_joints]
        k = np.concatenate([here[None], k[1:] if np.linalg.norm(k[0] - here) <= START_TOLERANCE else k])
        if not np.any(np.linalg.norm(np.diff(k, axis=0), axis=-1) > S.DUPLICATE_DISTANCE):
            self._reject("set_path: the path must leave the current position (all knots coincide with it)")
        report = self._prepare(k, "set_path")
        try:
            path = S.make_path(report.knots, self.max_knots)
        except ValueError as e:  # more knots than max_knots
            self._reject(f"set_path: {e}")
        track = self._core.track._replace(path=path, n_knots=path.n_knots, s=jnp.zeros(()), s_start=jnp.zeros(()),
                                          braking=jnp.zeros((), bool))
        self._accept(track)
        self.path_report = report

    def set_cartesian_path(self, points, robot=None) -> None:
        """:meth:`set_path` of a tool path ``points [W, 3]`` [m] of the robot's target point, made
        a joint path by IK from the current position (:mod:`mjx_pathtrack.paths.cartesian`:
        continuity, limits, self-collision); ``robot``: default the policy's (its manifest's).
        Raises :class:`PathError` naming the waypoint that cannot be followed."""
        from mjx_pathtrack.paths.cartesian import tool_path_to_joints
        from mjx_pathtrack.robots import registry as robots

        if robot is None:
            if self.robot_name is None:
                raise ValueError("set_cartesian_path: pass the robot (the policy has no manifest naming it)")
            robot = robots.load_robot(self.robot_name)
        try:
            joints = tool_path_to_joints(robot, points, self.position, "set_cartesian_path").joints
        except DatasetError as e:
            self._reject(str(e))
        self.set_path(joints[:, self.path_joints])

    def update_path(self, new_knots) -> None:
        """Replace the reference ahead of the current arc position by a spline through
        ``new_knots [m, n_path]`` (continuous in position and direction; paper 000 Fig. 4), at any
        time. Raises :class:`PathError` for a bad path or one with more than ``max_knots - 2``
        knots; the tracker then brakes and keeps its previous reference."""
        if not self._has_path:
            raise RuntimeError("update_path before set_path: there is no reference to adjust")
        k = self._checked_knots(new_knots, "update_path", min_count=1)
        report = None
        if self.knot_rule is not None:   # the curve replace_ahead builds from q(s), re-knotted
            s = jnp.clip(self._core.track.s, 0.0, self.path.length)
            here = np.asarray(S.point_at(self.path, s), np.float64)
            tangent = np.asarray(S.tangent_at(self.path, s), np.float64)
            report = self._prepare(np.concatenate([here[None], k]), "update_path", tangent)
            k = report.knots[1:]
        if len(k) > self.max_knots - 2:
            self._reject(f"update_path: {len(k)} knots, at most max_knots - 2 = {self.max_knots - 2} fit")
        padded = np.concatenate([k, np.repeat(k[-1:], self.max_knots - len(k), 0)])
        track, count, expected = self._replace_fn(self._core.track, jnp.asarray(padded, jnp.float32),
                                                  jnp.asarray(len(k), jnp.int32))
        if int(count) != int(expected) or not bool(jnp.all(jnp.isfinite(track.path.table_s))):
            self._reject(f"update_path: the new reference could not be built "
                         f"({int(count)} of {int(expected)} knots kept)")
        self._accept(track)
        self.path_report = report

    # -- decision step ----------------------------------------------------------------------

    def step(self) -> TrackerOutput:
        """One decision step: query the policy, return the setpoints of the next ``dt``.

        An invalid action (NaN/inf, wrong shape, not numeric) does not raise: the tracker brakes
        and reports ``fault``. An exception raised *by the policy* propagates, with the tracker's
        state untouched (calling ``step`` again retries the same decision)."""
        action, fault = self._query_policy()
        self._core, out = self._step_fn(self._core, action, jnp.asarray(fault is not None))
        if fault is not None and self._fault is None:
            self._fault = fault
        p_set, v_set, a_set, jerk, s, length, reached, braking, stopped, obs = jax.device_get(out)
        self._obs = out[-1]
        self._time_steps += 1
        status = Status.STOPPED if stopped else Status.BRAKING if braking else Status.TRACKING
        self._last_status = status
        t0 = (self._time_steps - 1) * self.dt
        return TrackerOutput(time=t0 + self.controller_dt * np.arange(1, self.substeps + 1), position=p_set,
                             velocity=v_set, acceleration=a_set, jerk=jerk, status=status, s=float(s),
                             path_length=float(length), progress=float(s / max(length, 1e-12)),
                             reached_end=bool(reached), fault=self._fault if braking else None, action=action)

    def observation(self) -> np.ndarray:
        """The observation ``[obs_size]`` the next :meth:`step` gives the policy."""
        return np.asarray(self._obs)

    # -- jitted cores -----------------------------------------------------------------------

    # -- helpers ----------------------------------------------------------------------------

    def _query_policy(self) -> tuple[np.ndarray, str | None]:
        raw = self.policy(np.asarray(self._obs))
        try:
            action = np.asarray(raw, np.float32)
        except (TypeError, ValueError):
            return np.zeros(self.n_joints, np.float32), f"policy returned a non-numeric action ({type(raw).__name__})"
        if action.shape != (self.n_joints,):
            return np.zeros(self.n_joints, np.float32), (f"policy returned an action of shape {action.shape}, "
                                                         f"expected ({self.n_joints},)")
        if not np.all(np.isfinite(action)):
            return np.zeros(self.n_joints, np.float32), "policy returned NaN or inf"
        return action, None

    def _checked_knots(self, knots, where: str, min_count: int = 1) -> np.ndarray:
        try:
            k = np.asarray(knots, np.float64)
        except (TypeError, ValueError) as e:
            self._reject(f"{where}: knots are not a numeric [K, {self.n_path}] array ({e})")
        if k.ndim != 2 or k.shape[1] != self.n_path:
            self._reject(f"{where}: knots must be [K, {self.n_path}] (path joints {self.path_joints.tolist()}), "
                         f"got shape {k.shape}")
        if len(k) < min_count:
            self._reject(f"{where}: need at least {min_count} knot(s), got {len(k)}")
        bad = np.argwhere(~np.isfinite(k))
        if bad.size:
            i, j = bad[0]
            self._reject(f"{where}: knot {i}, path joint {j} is {k[i, j]} (NaN/inf not allowed)")
        try:
            k, self._limit_shift = into_limits(k, SimpleNamespace(pos_min=self._lo, pos_max=self._hi),
                                               self.limit_allowance, [f"path joint {j}" for j in range(self.n_path)],
                                               where)
        except DatasetError as e:
            self._reject(str(e))
        return k

    def _prepare(self, k: np.ndarray, where: str, start_slope=None) -> PreparedPath:
        """The knots ``k`` (inside the limits) re-knotted by :attr:`knot_rule`, with the report."""
        lim = SimpleNamespace(pos_min=self._lo, pos_max=self._hi)
        try:
            prepared = prepare_path(k, lim, self.knot_rule, name=where, start_slope=start_slope)
        except DatasetError as e:
            self._reject(str(e))
        return dataclasses.replace(prepared, limit_shift=self._limit_shift)

    def _reject(self, message: str) -> NoReturn:
        """Brake from now on (the held reference and state stay as they were) and raise."""
        self._fault = message
        self._core = self._core._replace(fault=jnp.ones((), bool))
        if self._last_status is Status.TRACKING:
            self._last_status = Status.BRAKING
        raise PathError(message)

    def _accept(self, track: TrackState) -> None:
        self._has_path = True
        self._core = Core(track, jnp.zeros((), bool))
        self._fault = None
        self._obs = self._obs_fn(track)
        self._last_status = Status.BRAKING if bool(track.braking) else Status.TRACKING

    def _at_rest(self, v, a) -> bool:
        return bool(at_rest(self.limits, jnp.asarray(v), jnp.asarray(a)))

    def _joint_vector(self, x, name: str) -> np.ndarray:
        n = self.limits.n_joints
        x = np.zeros(n) if x is None else np.asarray(x, np.float64)
        if x.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name} contains NaN or inf")
        return x.astype(np.float32)


#: jitted cores per tracker configuration (limits, dt, rate, N, knot scale, path joints, max_knots)
_COMPILED: dict = {}
_checked_range = jax.jit(L.safe_acceleration_range_checked, static_argnums=(4,))
