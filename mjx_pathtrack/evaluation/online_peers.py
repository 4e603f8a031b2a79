"""Online peers of the learned tracker: classical controllers that know what the policy knows.

The policy sees its kinematic state and the next ``N`` knots, and decides every ``dt``. A peer
here gets exactly that: the current state, and the reference curve from the robot's place on it to
the ``N``-th knot ahead (the end knot once it is among them); nothing beyond. It is built on its
real library, never re-implemented:

:class:`RuckigLookahead` (``ruckig``, the standard online jerk-limited generator): every control
  cycle (``dt / substeps``, 240 Hz by default) a time-optimal jerk-limited motion from the current
  state towards a look-ahead point ``lookahead`` rad of arc ahead of the robot's projection on the
  path, arriving there with the tangent speed that still lets it stop at the end of the window
  (``speed_factor`` of the joints' velocity limits along the tangent, capped by braking at the
  acceleration limits), at rest where the window ends. What many integrators run today; it cuts
  corners, so its deviation matters as much as its time.

:func:`run_peer` runs a peer over episodes of an environment's references and returns a
:class:`~mjx_pathtrack.evaluation.rollout.Rollout`, so that the metrics, deviations and the limit
audit are computed by the same code as the policy's (:func:`rollout.episode_table`). Episodes end
as the policy's do: at the path end at rest (within ``end_knot_tolerance`` of the end knot, below
``stop_velocity`` / ``stop_acceleration``: the stop time), on the deviation limit, or when the time
budget runs out. A peer's deviation for that limit is measured at its own place on the path (the
closest reference point, searched forward from its last place); the policy's environment measures
at equal arc length (its arc position advances by the length it moved), which is stricter for a
motion that cuts corners. The tables report both measures for every controller: the joint
deviation at equal arc length and the Cartesian contour deviation (distance from the reference's
tool curve). ``compute_s``: the wall time the peer's library took per decision step (every call of that step).

Not here yet: receding-horizon TOPP-RA and TOPP3 (a time-optimal parameterisation of the window
every decision step, executed jerk-limited). TOPP-RA's profile switches its acceleration inside a
decision step; executed through a constant-jerk step (its acceleration at ``dt``, or the
acceleration that lands on its position at ``dt``, clipped into the safe range) or followed by
Ruckig at 240 Hz, the attempts left the path within a few decisions on the shipped policy's test
paths (docs/results.md "Online peers"). One TOPP3 solve (``copp-py``) takes ~1 s per 7-joint path,
10x a decision step.
"""

from __future__ import annotations

import dataclasses
import time as _time

import numpy as np

from mjx_pathtrack.core import reward as R
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.core.spline_fit import _horner, _locate
from mjx_pathtrack.evaluation import rollout as E

#: arc-length spacing [rad] of the search for the robot's place on the path
PROJECTION_SPACING = 0.005
#: share of a limit a peer's target state may use (Ruckig refuses a target *at* a limit after rounding)
CAP = 1.0 - 1e-6
#: instants per control cycle at which the limit audit reads Ruckig's trajectory
AUDIT_SAMPLES = 6
#: how far [rad] ahead of its last place the search for the robot's place on the path looks
PROJECTION_REACH = 0.5


class ReferenceView:
    """One episode's reference (a single :class:`~mjx_pathtrack.core.spline.Path`) in NumPy float64:
    points, tangents and the knot window at arc positions [rad] (the package's own spline)."""

    def __init__(self, path: S.Path, s_start: float, n_next: int):
        self.path = path
        self._arrays = [np.asarray(getattr(path, k), np.float64) for k in ("table_s", "table_dtds", "h", "coeffs")]
        self._m = path.samples_per_segment
        self.n_knots = int(path.n_knots)
        self._valid = (self.n_knots - 1) * self._m
        self.knot_s = np.asarray(path.knot_s, np.float64)[:self.n_knots]
        self.length = float(self.knot_s[-1])
        self.s_start = float(s_start)
        self.n_next = int(n_next)
        self.end = self.point(self.length)

    def _locate(self, s):
        table_s, table_dtds, h, coeffs = self._arrays
        seg, t = _locate(table_s, table_dtds, h, coeffs, self._m, self._valid, np.asarray(s, np.float64), np)
        return coeffs[seg], t

    def point(self, s) -> np.ndarray:
        """Reference position ``[..., n]`` at arc positions ``s [...]`` (clamped to the path)."""
        c, t = self._locate(s)
        return _horner(c, t, np)

    def tangent(self, s) -> np.ndarray:
        """Unit tangent ``dq/ds [..., n]`` at ``s [...]``."""
        c, t = self._locate(s)
        tt = np.asarray(t)[..., None]
        d1 = c[..., 1, :] + tt * (2.0 * c[..., 2, :] + 3.0 * tt * c[..., 3, :])
        return d1 / np.maximum(np.linalg.norm(d1, axis=-1, keepdims=True), 1e-20)

    def window_end(self, s: float) -> tuple[float, bool]:
        """Arc position [rad] of the ``N``-th knot after the last knot at or before ``s``, and
        whether it is the end knot: how far the policy's observation reaches."""
        i0 = int(np.clip(np.searchsorted(self.knot_s, s, side="right") - 1, 0, self.n_knots - 1))
        i = min(i0 + self.n_next, self.n_knots - 1)
        return float(self.knot_s[i]), i == self.n_knots - 1

    def project(self, q: np.ndarray, s_prev: float, s_max: float) -> float:
        """The robot's place on the path: the arc position in ``[s_prev, min(s_prev + reach, s_max)]``
        whose reference point is closest to ``q`` (searched every ``PROJECTION_SPACING`` rad)."""
        hi = min(s_prev + PROJECTION_REACH, s_max)
        s = np.linspace(s_prev, hi, max(2, int(np.ceil((hi - s_prev) / PROJECTION_SPACING)) + 1))
        return float(s[np.argmin(np.linalg.norm(self.point(s) - q, axis=-1))])


def path_speed_cap(view: ReferenceView, s: float, s_end: float, vel: np.ndarray, acc: np.ndarray) -> float:
    """Largest speed along the path [rad/s] at ``s``: the joints' velocity limits along the tangent
    there, and a stop at the acceleration limits along it before ``s_end`` (``sqrt(2 a d)``)."""
    tangent = np.abs(view.tangent(s))
    v_cap = float(np.min(vel / np.maximum(tangent, 1e-9)))
    a_cap = float(np.min(acc / np.maximum(tangent, 1e-9)))
    return min(v_cap, float(np.sqrt(2.0 * a_cap * max(s_end - s, 0.0))))


@dataclasses.dataclass
class RuckigLookahead:
    """Ruckig towards a look-ahead point, every control cycle (see the module docstring).
    ``lookahead`` [rad of arc]; ``speed_factor``: the share of the tangent speed cap the target
    velocity asks for (1: as fast as the velocity limits allow along the path there). Defaults:
    the fastest of a 4 x 4 grid on 10 whole training paths of the iiwa's mixed set that reached
    every end within every limit (``python benchmarks/online_peers.py policies/iiwa --tune``,
    docs/results.md "Online peers"); faster settings overshoot the position limits (Ruckig's
    community version takes none) or leave the path."""

    lookahead: float = 0.3
    speed_factor: float = 0.3
    name: str = "Ruckig look-ahead"

    def __post_init__(self):
        if not (self.lookahead > 0 and 0 < self.speed_factor <= 1):
            raise ValueError(f"lookahead must be > 0 and speed_factor in (0, 1], got {self.lookahead}, "
                             f"{self.speed_factor}")

    def decide(self, view: ReferenceView, s: float, p, v, a, limits: dict, dt: float, substeps: int):
        """One decision step: ``substeps`` Ruckig cycles. Returns the states at the cycle ends
        ``(p, v, a) [substeps, n]``, the library's wall time [s] and the exact states of Ruckig's
        trajectory at ``AUDIT_SAMPLES`` instants per cycle ``(p, v, a) [substeps * audit_samples, n]``
        (for the limit audit: Ruckig's motion between cycle ends is not one constant-jerk piece)."""
        from ruckig import InputParameter, OutputParameter, Result, Ruckig

        n = len(p)
        h = dt / substeps
        otg = Ruckig(n, h)
        inp, out = InputParameter(n), OutputParameter(n)
        inp.max_velocity, inp.max_acceleration, inp.max_jerk = limits["vel"], limits["acc"], limits["jerk"]
        ps, vs, as_, fine = [], [], [], []
        spent = 0.0
        for _ in range(substeps):
            s_end, _ = view.window_end(s)
            s = view.project(p, s, s_end)
            target = min(s + self.lookahead, s_end)
            speed = 0.0 if target >= s_end - 1e-9 else \
                self.speed_factor * path_speed_cap(view, target, s_end, limits["vel"], limits["acc"])
            inp.current_position, inp.current_velocity, inp.current_acceleration = p, v, a
            inp.target_position = view.point(target)
            inp.target_velocity = np.clip(speed * view.tangent(target), -CAP * limits["vel"], CAP * limits["vel"])
            inp.target_acceleration = np.zeros(n)
            start = _time.perf_counter()
            result = otg.update(inp, out)
            spent += _time.perf_counter() - start
            if result not in (Result.Working, Result.Finished):
                raise RuntimeError(f"ruckig failed ({result}) at arc position {s:.4f}")
            # the cycle on Ruckig's trajectory (`out.time`: where this cycle ends on it; the same
            # trajectory is reused while the input follows it)
            fine += [out.trajectory.at_time(out.time - h + h * (i + 1) / AUDIT_SAMPLES) for i in range(AUDIT_SAMPLES)]
            p, v, a = (np.array(x, np.float64) for x in (out.new_position, out.new_velocity, out.new_acceleration))
            ps.append(p), vs.append(v), as_.append(a)
        fine = tuple(np.asarray(x, np.float64) for x in zip(*fine))
        return np.array(ps), np.array(vs), np.array(as_), spent, fine


def sampled_ratios(lim, p: np.ndarray, v: np.ndarray, a: np.ndarray, h: float) -> np.ndarray:
    """``[4, n]`` limit ratios (as :func:`rollout.limit_ratios`) of a motion given by its exact states
    ``p, v, a [K, n]`` at instants ``h`` [s] apart: the largest |position| (mapped to [-1, 1] over
    the range), |velocity| and |acceleration| over the samples, and the largest mean jerk between
    neighbouring samples, each over its limit."""
    lo, hi = np.asarray(lim.pos_min, np.float64), np.asarray(lim.pos_max, np.float64)
    finite = np.isfinite(lo) & np.isfinite(hi)
    mid = np.where(finite, 0.5 * (lo + hi), 0.0)
    half = np.where(finite, 0.5 * (hi - lo), 1.0)
    pos = np.where(finite, np.max(np.abs(p - mid), axis=0) / half, 0.0)
    vel = np.max(np.abs(v), axis=0) / np.asarray(lim.vel, np.float64)
    acc = np.max(np.abs(a), axis=0) / np.asarray(lim.acc, np.float64)
    jerk = np.max(np.abs(np.diff(a, axis=0)), axis=0) / h / np.asarray(lim.jerk, np.float64)
    return np.stack([pos, vel, acc, jerk])


def run_peer(env, peer, paths: S.Path, s_start: np.ndarray, path_index: np.ndarray, p0: np.ndarray,
             change: tuple[int, np.ndarray] | None = None) -> tuple[E.Rollout, np.ndarray]:
    """Run ``peer`` on the episodes ``paths [B]`` (a stacked reference batch, e.g. a policy
    rollout's ``ro.paths``) from ``s_start [B]`` [rad], starting at rest at ``p0 [B, n]``.
    ``change = (k, knots [B, m, n])``: before decision step ``k`` the reference ahead of each
    robot's place is replaced by a spline through its ``knots``
    (:func:`~mjx_pathtrack.core.spline.replace_ahead`, as ``OnlineTracker.update_path``); the peer
    sees the new window from then on. Returns a :class:`~mjx_pathtrack.evaluation.rollout.Rollout`
    (for ``rollout.episode_table``; its references are the final ones, the part behind the change
    unchanged) and ``compute_s [T, B]``: the library's wall time per decision step (NaN after the end)."""
    import jax

    cfg = env.config
    dt, substeps = float(cfg.dt), int(cfg.substeps)
    pj = np.asarray(env.path_joints)
    if len(pj) != len(np.asarray(env.home)):
        raise ValueError("online peers drive every joint along the path: the environment has joints off the path")
    lim = env.limits
    limits = {k: np.asarray(getattr(lim, k), np.float64) for k in ("vel", "acc", "jerk")}
    steps = cfg.max_episode_steps()
    B, n = len(s_start), p0.shape[-1]
    executed = np.zeros((steps, B, substeps + 1, n))
    rec = {k: np.zeros((steps, B, n)) for k in ("p", "v", "a")}
    ratios = np.zeros((steps, B, 4, n))
    live = np.zeros((steps, B), bool)
    progress, deviation, compute = (np.full((steps, B), np.nan) for _ in range(3))
    metrics = {k: np.full(B, np.nan) for k in ("end_time", "stop_time")}
    counts = {k: np.zeros(B) for k in ("steps", "success", "terminated", "progress", "dev_sum", "dev_max")}
    done = np.zeros(B, bool)
    weights = cfg.deviation_weights
    final = []
    for b in range(B):
        path = jax.tree.map(lambda x: x[b], paths)
        view = ReferenceView(path, float(s_start[b]), cfg.n_next)
        p, v, a = np.asarray(p0[b], np.float64), np.zeros(n), np.zeros(n)
        s = view.s_start
        for k in range(steps):
            if change is not None and k == change[0]:
                path = S.replace_ahead(path, np.float32(s), np.asarray(change[1][b], np.float32))
                view = ReferenceView(path, float(s_start[b]), cfg.n_next)
            ps, vs, as_, spent, fine = peer.decide(view, s, p, v, a, limits, dt, substeps)
            ratios[k, b] = sampled_ratios(lim, np.concatenate([p[None], fine[0]]), np.concatenate([v[None], fine[1]]),
                                          np.concatenate([a[None], fine[2]]), dt / (substeps * AUDIT_SAMPLES))
            executed[k, b] = np.concatenate([p[None], ps])
            rec["p"][k, b], rec["v"][k, b], rec["a"][k, b] = ps[-1], vs[-1], as_[-1]
            live[k, b], compute[k, b] = True, spent
            # the peer's place on the path after each cycle, and its deviation there (weighted like
            # the environment's)
            s_end, _ = view.window_end(s)
            places = []
            for q in ps:
                s = view.project(q, s, s_end)
                places.append(s)
            d = np.asarray(R.weighted_deviation(view.point(np.asarray(places)), ps, weights), np.float64)
            p, v, a = ps[-1], vs[-1], as_[-1]
            progress[k, b] = (s - view.s_start) / max(view.length - view.s_start, 1e-9)
            deviation[k, b] = d.max()
            counts["dev_sum"][b] += d.mean()
            counts["dev_max"][b] = max(counts["dev_max"][b], d.max())
            t = (k + 1) * dt
            at_end = np.max(np.abs(p - view.end)) <= cfg.end_knot_tolerance
            if at_end and np.isnan(metrics["end_time"][b]):
                metrics["end_time"][b] = t
            stopped = at_end and np.max(np.abs(v)) < cfg.stop_velocity and np.max(np.abs(a)) < cfg.stop_acceleration
            terminated = cfg.terminate_deviation is not None and d.max() > cfg.terminate_deviation
            counts["steps"][b] = k + 1
            counts["progress"][b] = progress[k, b]
            if stopped and not terminated:
                metrics["stop_time"][b], counts["success"][b], done[b] = t, 1.0, True
                break
            if terminated:
                counts["terminated"][b], done[b] = 1.0, True
                break
        else:
            done[b] = True   # the time budget ran out
        final.append(path)
    m = E.EpisodeMetrics(np.zeros(B), counts["steps"], metrics["end_time"], metrics["stop_time"],
                         counts["dev_sum"] / np.maximum(counts["steps"], 1), counts["dev_max"], counts["success"],
                         counts["terminated"], counts["progress"], np.zeros(B))
    ro = E.Rollout(executed, rec["p"], rec["v"], rec["a"], np.zeros((steps, B, 0)), live, ratios,
                   np.asarray(p0, np.float64), paths if change is None else S.stack_paths(final),
                   np.asarray(s_start), np.asarray(path_index), done, m,
                   progress, deviation, {})
    return ro, compute


def peer_table(env, peer, ro: E.Rollout, robot=None, measure: list | None = None, toppra: bool = True
               ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """``peer`` on the episodes of a policy's recorded batch ``ro`` (same references, start arc
    positions and start states): the per-episode table of :func:`rollout.episode_table` (with
    ``toppra``: TOPP-RA's durations and the stop-time ratio to them, as ``evaluate.py``'s) and the
    library's wall time per decision ``[T, B]`` (NaN after each episode's end)."""
    import jax

    from mjx_pathtrack.evaluation import baseline

    peer_ro, compute = run_peer(env, peer, ro.paths, ro.s_start, ro.path_index, ro.p0)
    table = E.episode_table(env, peer_ro, robot, measure=measure)
    if toppra:
        table.update(baseline.toppra_columns(env, jax.tree.map(np.asarray, ro.paths), ro.s_start, table["stop_time_s"]))
    return table, compute


def summary_row(name: str, table: dict[str, np.ndarray], compute_s=None) -> dict:
    """One controller's figures on a set of episodes (its :func:`rollout.episode_table`, with the
    TOPP-RA columns where present): end reached, mean stop time [s], mean ratio to TOPP-RA, joint
    deviation at equal arc length (mean / max / final, episode means) [rad], Cartesian contour
    deviation [cm] (with a robot), the limit audit and its worst quantity, the compute per decision
    ``compute_s`` (any shape, NaN ignored; None: not measured) as mean / max [ms], terminations."""
    summary = E.aggregate(table)
    ratio = table.get("ratio_to_toppra", np.full(summary["episodes"], np.nan))
    audit = summary["limit_audit"]
    compute = np.full(1, np.nan) if compute_s is None else np.asarray(compute_s, np.float64)
    finite = compute[np.isfinite(compute)]
    return {"controller": name, "episodes": summary["episodes"], "end_reached": summary["end_reached_rate"],
            "stop_time_s": summary["stop_time_s_mean"],
            "ratio_to_toppra": float(np.nanmean(ratio)) if np.isfinite(ratio).any() else float("nan"),
            "joint_dev_mean": float(np.mean(table["joint_dev_mean"])),
            "joint_dev_max": float(np.mean(table["joint_dev_max"])),
            "joint_dev_final": float(np.mean(table["joint_dev_final"])),
            "contour_cm": float(np.mean(table["cart_contour_dev_cm_mean"])) if "cart_contour_dev_cm_mean" in table
            else None,
            "audit": audit, "audit_worst": max(("pos", "vel", "acc", "jerk"), key=lambda q: audit[q]),
            "audit_ok": audit["ok"],
            "compute_mean_ms": 1e3 * float(finite.mean()) if finite.size else float("nan"),
            "compute_max_ms": 1e3 * float(finite.max()) if finite.size else float("nan"),
            "terminations": summary["termination"]}
