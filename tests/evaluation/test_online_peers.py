"""Online peers (mjx_pathtrack.evaluation.online_peers): a known answer on a straight segment, the
limits at every sampled instant on curved paths, and that a peer knows nothing beyond the next N
knots."""

import jax
import numpy as np
import pytest

from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
from mjx_pathtrack.evaluation import online_peers as P
from mjx_pathtrack.evaluation import rollout as E
from mjx_pathtrack.robots import registry as robots

DT = 0.1


@pytest.fixture(scope="module")
def iiwa():
    return robots.load_robot("iiwa", dt=DT)


def _env(iiwa, paths, n_next=8, duration=6.0):
    cfg = EnvConfig(start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0, duration=duration, n_next=n_next,
                    end_knot_tolerance=1e-3, stop_velocity=1e-3, stop_acceleration=1e-3)
    return PathTrackingEnv(iiwa.limits, S.stack_paths(paths), 0.9, cfg, home=iiwa.q0)


def _run(env, peer, count):
    paths = jax.tree.map(lambda x: x[:count], env.paths)
    p0 = np.asarray(E.reference_points(paths, jax.numpy.zeros((count, 1))))[:, 0]
    return P.run_peer(env, peer, paths, np.zeros(count), np.arange(count), p0)


def s_curve_time(distance, vel, acc, jerk):
    """Analytic time-optimal rest-to-rest duration [s] of one jerk-limited joint (the 7-phase
    S-curve): accelerating to the peak speed v takes ``v/A + A/J`` (``2 sqrt(v/J)`` if A is not
    reached) and covers half of ``v`` times that; the peak is ``vel`` or what the distance allows."""
    def ramp(v):
        return v / acc + acc / jerk if v * jerk >= acc * acc else 2.0 * np.sqrt(v / jerk)

    if vel * ramp(vel) <= distance:
        return 2.0 * ramp(vel) + (distance - vel * ramp(vel)) / vel
    lo, hi = 0.0, vel
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mid * ramp(mid) < distance else (lo, mid)
    return 2.0 * ramp(lo)


def test_s_curve_time_matches_its_limits():
    # a long move at the speed limit: 2 ramps of v/A + A/J and the cruise
    assert s_curve_time(10.0, 1.0, 2.0, 8.0) == pytest.approx(2 * (0.5 + 0.25) + (10.0 - 0.75) / 1.0)
    # a short move never reaching A: four jerk phases, distance 2 J t^3 -> t = (d / 2J)^(1/3)
    assert s_curve_time(0.002, 1.0, 2.0, 8.0) == pytest.approx(4 * (0.002 / 16.0) ** (1 / 3), rel=1e-6)


@pytest.mark.parametrize("length", [0.05, 1.2])
def test_straight_segment_in_one_window_takes_the_jerk_limited_optimum(iiwa, length):
    """The whole segment in view and a look-ahead past its end: Ruckig's target is the end knot at
    rest from the start, so the motion is the time-optimal jerk-limited one, whose duration is
    known in closed form; the peer's stop time is the decision step that contains it."""
    knots = np.zeros((4, 7))
    knots[:, 0] = np.linspace(0.0, length, 4)
    knots[:, 1] = 0.5
    env = _env(iiwa, [S.make_path(knots)])
    ro, compute = _run(env, P.RuckigLookahead(lookahead=10.0, speed_factor=1.0), 1)
    lim = iiwa.limits
    optimum = s_curve_time(length, float(lim.vel[0]), float(lim.acc[0]), float(lim.jerk[0]))
    assert ro.metrics.stop_time[0] == pytest.approx(DT * np.ceil(optimum / DT - 1e-6), abs=1e-9)
    assert ro.done[0] and ro.metrics.success[0] == 1
    live = ro.live[:, 0]
    np.testing.assert_allclose(ro.p[live, 0][:, 1:], knots[0, 1:][None].repeat(live.sum(), 0), atol=1e-9)
    np.testing.assert_allclose(ro.p[live, 0][-1, 0], length, atol=1e-4)
    assert np.all(np.isfinite(compute[live, 0])) and np.all(compute[live, 0] > 0)


def test_limits_hold_at_every_sampled_instant_on_curved_paths(iiwa):
    """Fast settings on random curves: every sampled state of Ruckig's motion within every limit."""
    rng = np.random.default_rng(3)
    paths = []
    for _ in range(3):
        steps = rng.normal(0.0, 0.15, (12, 7))
        knots = np.clip(np.asarray(iiwa.q0) + np.cumsum(steps, axis=0), np.asarray(iiwa.limits.pos_min) + 0.2,
                        np.asarray(iiwa.limits.pos_max) - 0.2)
        paths.append(S.make_path(knots))
    env = _env(iiwa, paths, duration=8.0)
    ro, _ = _run(env, P.RuckigLookahead(lookahead=0.3, speed_factor=1.0), 3)
    table = E.episode_table(env, ro, iiwa)
    for q in ("pos", "vel", "acc", "jerk"):
        assert np.all(table[f"max_{q}_ratio"] <= 1.0 + E.AUDIT_TOLERANCE), (q, table[f"max_{q}_ratio"])
    # and the audit is not vacuous: this motion uses its velocity, acceleration and jerk limits
    assert np.max(table["max_vel_ratio"]) > 0.9 and np.max(table["max_acc_ratio"]) > 0.9
    assert np.max(table["max_jerk_ratio"]) > 0.9


def test_sampled_ratios_of_a_known_motion(iiwa):
    lim = iiwa.limits
    h = 0.001
    t = np.arange(11)[:, None] * h
    jerk = 0.5 * np.asarray(lim.jerk)
    a = jerk * t
    v = 0.5 * jerk * t ** 2
    p = np.asarray(lim.pos_max) - 0.1 + jerk * t ** 3 / 6.0
    r = P.sampled_ratios(lim, p, v, a, h)
    np.testing.assert_allclose(r[3], 0.5, rtol=1e-9)   # the mean jerk between samples
    np.testing.assert_allclose(r[2], a[-1] / np.asarray(lim.acc), rtol=1e-9)
    half = 0.5 * (np.asarray(lim.pos_max) - np.asarray(lim.pos_min))
    np.testing.assert_allclose(r[0], (half - 0.1 + jerk * t[-1] ** 3 / 6.0) / half, rtol=1e-9)


def test_a_peer_looks_no_further_than_the_next_knots(iiwa):
    """Every arc position a peer asks the reference about lies before the N-th knot ahead of its
    place (the window the policy's observation shows), at every cycle of a whole path."""
    knots = np.zeros((14, 7))
    knots[:, 0] = np.linspace(0.0, 1.3, 14)
    knots[:, 1] = 0.5 + 0.1 * np.sin(np.arange(14))
    path = S.make_path(knots)
    asked = []

    class Watched(P.ReferenceView):
        """Records every arc position asked about beside the end of the window last asked for
        (the peer asks for its window at its place on the path every cycle)."""
        window = None

        def window_end(self, s):
            end = super().window_end(s)
            self.window = end[0]
            return end

        def point(self, s):
            if self.window is not None:
                asked.append((np.max(s), self.window))
            return super().point(s)

        def tangent(self, s):
            asked.append((np.max(s), self.window))
            return super().tangent(s)

    view = Watched(path, 0.0, 3)
    lim = iiwa.limits
    limits = {k: np.asarray(getattr(lim, k), np.float64) for k in ("vel", "acc", "jerk")}
    p, v, a = knots[0].copy(), np.zeros(7), np.zeros(7)
    place = 0.0
    for _ in range(40):
        ps, vs, as_, _, _ = P.RuckigLookahead(lookahead=0.5, speed_factor=1.0).decide(view, place, p, v, a, limits,
                                                                                     DT, 24)
        p, v, a = ps[-1], vs[-1], as_[-1]
        place = view.project(p, place, P.ReferenceView.window_end(view, place)[0])
    s_asked, s_window = np.array(asked).T
    assert len(asked) > 100 and np.all(s_asked <= s_window + 1e-9)
    assert np.any(s_window < view.length - 0.3)   # (a window short of the end was in force)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="lookahead must be > 0"):
        P.RuckigLookahead(lookahead=0.0)
    with pytest.raises(ValueError, match="speed_factor in"):
        P.RuckigLookahead(speed_factor=1.5)


def test_a_path_change_in_mid_motion_is_followed_to_the_new_end(iiwa):
    """Joint 1 runs along a line; before decision 6 the path ahead turns to joint 3: the motion
    up to then is the unchanged run's, the peer then follows the new window to the new end knot,
    within every limit at every sampled instant."""
    knots = np.zeros((8, 7))
    knots[:, 0] = np.linspace(0.0, 1.4, 8)
    knots[:, 1] = 0.5
    env = _env(iiwa, [S.make_path(knots, max_knots=16)], duration=8.0)   # (room for the new knots)
    new = np.zeros((1, 4, 7))
    new[0, :, 0] = 0.9
    new[0, :, 1] = 0.5
    new[0, :, 2] = np.linspace(0.2, 0.8, 4)
    peer = P.RuckigLookahead(lookahead=0.3, speed_factor=0.5)
    plain, _ = _run(env, peer, 1)
    paths = jax.tree.map(lambda x: x[:1], env.paths)
    changed, _ = P.run_peer(env, peer, paths, np.zeros(1), np.arange(1), np.asarray(plain.p0), change=(6, new))
    np.testing.assert_array_equal(changed.executed[:6, 0], plain.executed[:6, 0])
    assert not np.allclose(changed.executed[6, 0], plain.executed[6, 0])
    assert changed.metrics.success[0] == 1
    live = changed.live[:, 0]
    np.testing.assert_allclose(changed.p[live, 0][-1], new[0, -1], atol=1e-3)
    table = E.episode_table(env, changed, iiwa)
    for q in ("pos", "vel", "acc", "jerk"):
        assert table[f"max_{q}_ratio"][0] <= 1.0 + E.AUDIT_TOLERANCE, q
    # the final reference is the changed one: it ends at the new end knot
    np.testing.assert_allclose(np.asarray(changed.paths.knots)[0, int(changed.paths.n_knots[0]) - 1], new[0, -1],
                               atol=1e-6)
