"""OnlineTracker: streamed and adjusted references, every controller-rate setpoint audited."""

import numpy as np
import pytest

import jax
import jax.numpy as jnp

from pathlib import Path

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.deploy.controller import OnlineTracker, PathError, Status
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv

DT = 0.1
N_NEXT = 4
MAX_DIS = 0.5
LIM = iiwa.joint_limits(DT)
REPO = Path(__file__).resolve().parents[2]
N = 7
REL = 1e-6


_LO, _HI = np.asarray(LIM.pos_min, np.float64), np.asarray(LIM.pos_max, np.float64)
_VEL, _ACC = np.asarray(LIM.vel, np.float64), np.asarray(LIM.acc, np.float64)


def steering_policy(obs, speed=0.6):
    """Steer toward the next knot shown in the observation: decode the state and the knot from
    the observation, ask for a velocity toward the knot; action 0 keeps the acceleration and
    +-1 changes it by about J dt = 2 A (jerk range of the safe interval far from the limits)."""
    obs = np.asarray(obs, np.float64)
    p = _LO + 0.5 * (obs[:N] + 1.0) * (_HI - _LO)
    v, a = obs[N:2 * N] * _VEL, obs[2 * N:3 * N] * _ACC
    knot1 = _LO + 0.5 * (obs[4 * N:5 * N] + 1.0) * (_HI - _LO)
    d = knot1 - p
    v_des = speed * d / max(float(np.linalg.norm(d)), 0.05)
    a_des = np.clip(8.0 * (v_des - v), -_ACC, _ACC)
    return np.clip((a_des - a) / (2.0 * _ACC), -1.0, 1.0)


def random_policy(seed, kind="uniform"):
    rng = np.random.default_rng(seed)

    def policy(obs):
        if kind == "uniform":
            return rng.uniform(-1.0, 1.0, N)
        if kind == "bang":
            return rng.choice([-1.0, 1.0], N)
        if kind == "huge":   # outside [-1, 1]: clipped
            return rng.uniform(-1e6, 1e6, N)
        raise ValueError(kind)

    return policy


def tracker(policy, p0=None, controller_dt=1 / 200, max_knots=12, keep_knots=True, **kw):
    """(Trackers with equal settings share one compilation.) The knots as given by default: these
    tests follow given knots through the reference; the re-knotting has tests of its own."""
    p0 = np.zeros(N) if p0 is None else p0
    return OnlineTracker(policy, p0, controller_dt=controller_dt, limits=LIM, dt=DT, n_next=N_NEXT,
                         max_dis_between_knots=MAX_DIS, max_knots=max_knots, keep_knots=keep_knots, **kw)


class Auditor:
    """Checks every setpoint and the exact extrema inside every decision step against the limits,
    and the setpoints against the constant-jerk integration (float64) from the decision state."""

    def __init__(self, t: OnlineTracker):
        self.t = t
        self.state = tuple(np.asarray(x, np.float64) for x in (t.position, t.velocity, t.acceleration))
        self.outputs = []
        self.time = t.time
        lo, hi = np.asarray(LIM.pos_min, np.float64), np.asarray(LIM.pos_max, np.float64)
        self.lo, self.hi = lo, hi
        self.vel, self.acc, self.jerk = (np.asarray(x, np.float64) for x in (LIM.vel, LIM.acc, LIM.jerk))
        self.worst = 0.0

    def step(self):
        out = self.t.step()
        k = self.t.substeps
        assert out.position.shape == out.velocity.shape == out.acceleration.shape == (k, N)
        assert out.time.shape == (k,)
        np.testing.assert_allclose(out.time, self.time + self.t.controller_dt * np.arange(1, k + 1), rtol=0, atol=1e-9)
        self.time += DT
        p0, v0, a0 = self.state
        a1 = out.acceleration[-1].astype(np.float64)
        # setpoints = constant-jerk integration of the decision step at the controller instants
        t = self.t.controller_dt * np.arange(1, k + 1)[:, None]
        p_ref, v_ref, a_ref = (np.asarray(x) for x in L.integrate(p0, v0, a0, a1, DT, t))
        np.testing.assert_allclose(out.position, p_ref, rtol=0, atol=2e-5)
        np.testing.assert_allclose(out.velocity, v_ref, rtol=0, atol=2e-5)
        np.testing.assert_allclose(out.acceleration, a_ref, rtol=0, atol=1e-4)
        np.testing.assert_allclose(out.jerk, (a1 - a0) / DT, rtol=1e-5, atol=1e-3)
        # the last setpoint is the next decision state
        np.testing.assert_array_equal(out.position[-1], self.t.position)
        np.testing.assert_array_equal(out.velocity[-1], self.t.velocity)
        np.testing.assert_array_equal(out.acceleration[-1], self.t.acceleration)
        # every setpoint within the limits
        over = [np.max((out.position - self.hi) / np.maximum(np.abs(self.hi), 1)),
                np.max((self.lo - out.position) / np.maximum(np.abs(self.lo), 1)),
                np.max(np.abs(out.velocity) / self.vel) - 1, np.max(np.abs(out.acceleration) / self.acc) - 1]
        # exact extrema between the setpoints (constant jerk within the step)
        e = _extrema(p0, v0, a0, a1)
        over += [np.max((np.asarray(e.p_max) - self.hi) / np.maximum(np.abs(self.hi), 1)),
                 np.max((self.lo - np.asarray(e.p_min)) / np.maximum(np.abs(self.lo), 1)),
                 np.max(np.maximum(np.asarray(e.v_max), -np.asarray(e.v_min)) / self.vel) - 1,
                 np.max(np.asarray(e.a_abs) / self.acc) - 1, np.max(np.asarray(e.jerk_abs) / self.jerk) - 1]
        self.worst = max(self.worst, *map(float, over))
        assert self.worst <= REL, f"limit exceeded by {self.worst:.3g} (relative)"
        assert 0.0 <= out.s <= out.path_length + 1e-6
        self.state = (out.position[-1].astype(np.float64), out.velocity[-1].astype(np.float64), a1)
        self.outputs.append(out)
        return out

    def run_until_stopped(self, max_steps=400):
        for _ in range(max_steps):
            if self.step().status is Status.STOPPED:
                return self.outputs[-1]
        raise AssertionError(f"not stopped after {max_steps} steps; status {self.t.status}")


_extrema = jax.jit(lambda p, v, a0, a1: L.step_extrema(p, v, a0, a1, DT))


def straight_path(start, end, count=8):
    return start + np.linspace(0.0, 1.0, count)[:, None] * (end - start)


def test_stream_change_mid_motion_every_setpoint_within_limits():
    """Paper Fig. 4 online: stream a path, replace the part ahead mid-motion; every setpoint at
    1 kHz and every in-step extremum stays within the limits; the robot ends at rest."""
    t = tracker(steering_policy, controller_dt=1 / 1000, max_knots=12)
    audit = Auditor(t)
    knots = straight_path(np.zeros(N), np.array([1.2, -0.8, 1.0, 0.9, -1.0, 0.7, 1.5]), 10)[1:]
    t.set_path(knots)
    statuses = []
    for _ in range(12):
        statuses.append(audit.step().status)
    assert statuses == [Status.TRACKING] * 12
    assert np.max(np.abs(t.velocity)) > 0.2, "the robot should be moving when the path changes"
    s_before, p_before = t.s, t.position
    q_ref = np.asarray(S.point_at(t.path, t.s))
    # a detour ahead (more knots than fit behind the old ones: the knots behind the robot go)
    here = t.position
    detour = here + np.linspace(0.15, 1.0, 9)[:, None] * np.array([-0.6, 0.9, -0.4, 0.5, 0.8, -0.9, -0.5])
    t.update_path(detour)
    np.testing.assert_array_equal(t.position, p_before)
    assert t.s <= s_before + 1e-6
    path = t.path
    n = int(path.n_knots)
    np.testing.assert_allclose(np.asarray(path.knots[n - 9:n]), detour, atol=1e-6)
    np.testing.assert_allclose(np.asarray(S.point_at(path, t.s)), q_ref, atol=1e-4)  # cut point: reference at s
    # the observation shows the first detour knot next (knot0 is the cut point at the robot)
    obs = t.observation()
    lo, hi = np.asarray(LIM.pos_min), np.asarray(LIM.pos_max)
    np.testing.assert_allclose(obs[3 * N + N:3 * N + 2 * N], -1 + 2 * (detour[0] - lo) / (hi - lo), atol=1e-5)
    end = audit.run_until_stopped()
    seen = [o.status for o in audit.outputs]
    assert seen.index(Status.BRAKING) > 12 and seen[-1] is Status.STOPPED
    assert end.reached_end and end.progress == pytest.approx(1.0)
    assert np.linalg.norm(t.position - detour[-1]) < 0.25, "the steering policy should end near the new end"
    # stopped: holds exactly
    p_stop = t.position
    for _ in range(3):
        out = audit.step()
        assert out.status is Status.STOPPED
        np.testing.assert_array_equal(out.position, np.broadcast_to(p_stop, out.position.shape))
        np.testing.assert_array_equal(out.velocity, 0.0)
    assert t._step_fn._cache_size() == 1 and t._replace_fn._cache_size() == 1


@pytest.mark.parametrize("kind,seed", [("uniform", 0), ("bang", 1), ("huge", 2)])
def test_any_policy_output_keeps_the_limits_near_the_position_limits(kind, seed):
    """Random, bang-bang and out-of-range actions on a path hugging the position limits, with
    repeated path changes: all setpoints stay within the limits."""
    rng = np.random.default_rng(seed)
    hi = np.asarray(LIM.pos_max, np.float64)
    p0 = 0.9 * hi * rng.choice([-1, 1], N)
    t = tracker(random_policy(seed, kind), p0=p0)
    audit = Auditor(t)
    t.set_path(np.stack([np.clip(p0 + 0.3 * np.sign(p0), -hi, hi), hi * np.sign(p0), -0.5 * p0]))
    for i in range(60):
        audit.step()
        if i % 15 == 14:
            target = rng.uniform(-1, 1, (int(rng.integers(1, 8)), N)) * hi
            target[0] = hi * np.sign(rng.uniform(-1, 1, N))   # right at the limits
            t.update_path(target)
    assert audit.worst <= REL


def test_reference_replaced_at_every_step_keeps_capacity_and_limits():
    """A stream of adjustments, one per decision step, each with as many knots as fit: the knots
    behind the robot are dropped so that none is refused; every setpoint stays within limits."""
    rng = np.random.default_rng(5)
    t = tracker(steering_policy)
    audit = Auditor(t)
    hi = np.asarray(LIM.pos_max, np.float64)
    t.set_path(straight_path(np.zeros(N), 0.5 * hi, 6)[1:])
    for _ in range(30):
        audit.step()
        ahead = np.clip(t.position + np.cumsum(rng.uniform(-0.15, 0.25, (t.max_knots - 2, N)), axis=0), -hi, hi)
        t.update_path(ahead)
        assert int(t.path.n_knots) == t.max_knots
        assert t.status is Status.TRACKING
    assert audit.worst <= REL
    assert t._replace_fn._cache_size() == 1


@pytest.mark.parametrize("end_stop", ["fastest", "end_knot"])
def test_bad_path_mid_motion_errors_and_brakes_to_a_safe_stop(end_stop):
    """(A fault brakes every joint as fast as it can, whatever the stop at the path end.)"""
    t = tracker(steering_policy, end_stop=end_stop)
    audit = Auditor(t)
    t.set_path(straight_path(np.zeros(N), np.full(N, 1.5), 12)[1:])
    for _ in range(8):
        assert audit.step().status is Status.TRACKING
    moving = np.max(np.abs(t.velocity))
    assert moving > 0.2
    held = (t.position, t.velocity, t.acceleration, t.s, jax.tree.map(np.asarray, t.path))
    bad_paths = {
        "NaN": np.full((3, N), np.nan),
        "beyond the robot.s limits": np.full((3, N), 0.5) + np.eye(3, N) * 10.0,
        r"must be \[K, 7\]": np.zeros((3, 6)),
        "at most max_knots": np.zeros((11, N)) + np.linspace(0, 1, 11)[:, None],
        "numeric": [["a"] * N],
    }
    for match, knots in bad_paths.items():
        with pytest.raises(PathError, match=match):
            t.update_path(knots)
        # the held state and reference are untouched
        np.testing.assert_array_equal(t.position, held[0])
        np.testing.assert_array_equal(t.velocity, held[1])
        np.testing.assert_array_equal(t.acceleration, held[2])
        assert t.s == held[3]
        for a, b in zip(jax.tree.leaves(jax.tree.map(np.asarray, t.path)), jax.tree.leaves(held[4])):
            np.testing.assert_array_equal(a, b)
        assert t.status is Status.BRAKING and t.fault is not None
    first = audit.step()
    assert first.status is Status.BRAKING and "numeric" in first.fault
    end = audit.run_until_stopped(100)
    assert not end.reached_end, "it stopped because of the fault, not at the end"
    assert len(audit.outputs) < 8 + 1 + 20
    np.testing.assert_array_equal(t.velocity, 0.0)
    np.testing.assert_array_equal(t.acceleration, 0.0)
    # speed decreased monotonically while braking (no re-acceleration)
    speeds = [np.max(np.abs(o.velocity[-1])) for o in audit.outputs[8:]]
    assert all(b <= a + 1e-6 for a, b in zip(speeds, speeds[1:])) and speeds[0] < moving
    # a valid path afterwards clears the fault and tracking resumes from the stop
    t.update_path(np.full((2, N), 1.5) - np.array([[0.3], [0.0]]))
    assert t.fault is None
    out = audit.step()
    assert out.status is Status.TRACKING and out.fault is None
    assert audit.worst <= REL


def test_end_of_path_brakes_to_a_stop_and_holds():
    t = tracker(random_policy(3, "bang"), controller_dt=1 / 200)
    audit = Auditor(t)
    t.set_path(np.array([[0.1, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.1, 0.0, 0.0, 0.0, 0.0]]))
    end = audit.run_until_stopped(60)
    outs = audit.outputs
    i_end = next(i for i, o in enumerate(outs) if o.reached_end)
    # as in the environment: the step that reaches the end is still the policy's; braking after
    assert all(o.status is Status.TRACKING for o in outs[:i_end + 1])
    assert all(o.status is not Status.TRACKING for o in outs[i_end + 1:])
    assert end.progress == pytest.approx(1.0) and end.fault is None
    for _ in range(3):
        out = audit.step()
        assert out.status is Status.STOPPED
        np.testing.assert_array_equal(out.position, np.broadcast_to(end.position[-1], out.position.shape))
    # a path extension resumes tracking from the stop
    t.update_path(np.array([[0.5, 0.3, 0.2, 0.1, 0.0, 0.0, 0.0]]))
    assert audit.step().status is Status.TRACKING


def test_end_knot_stop_holds_at_the_end_knot():
    """With end_stop="end_knot" a bang-bang policy's run ends at rest with every joint within the
    tolerance of the end knot, every setpoint within the limits; the fastest stop ends farther."""
    knots = np.array([[0.1, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.1, 0.0, 0.0, 0.0, 0.0]])
    miss = {}
    for end_stop in ("fastest", "end_knot"):
        t = tracker(random_policy(3, "bang"), end_stop=end_stop, end_braking="predictive")
        audit = Auditor(t)
        t.set_path(knots)
        end = audit.run_until_stopped(80)
        assert end.reached_end and end.fault is None and audit.worst <= REL
        miss[end_stop] = np.abs(end.position[-1] - knots[-1])
    assert miss["end_knot"].max() <= 0.05 + 1e-3
    assert np.linalg.norm(miss["end_knot"]) < np.linalg.norm(miss["fastest"])


def test_end_tolerance_brakes_to_a_stop_short_of_the_end():
    """A policy that stalls short of the path end (here: it keeps the robot still) never reaches
    it; with end_tolerance covering the rest of the path the tracker brakes and stops."""
    knots = np.array([[0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0.02, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    for tolerance, expected in ((0.0, Status.TRACKING), (0.05, Status.STOPPED)):
        t = tracker(lambda obs: np.zeros(N), end_tolerance=tolerance)
        t.set_path(knots)
        outs = [t.step() for _ in range(3)]
        assert outs[-1].status is expected and outs[-1].reached_end is (tolerance > 0)
        assert outs[-1].progress < 1e-3


def test_policy_faults_brake_instead_of_raising():
    """NaN, a wrong shape or a non-numeric action: this and later steps brake (no exception)."""
    for bad in (np.full(N, np.nan), np.zeros(N + 1), "left"):
        calls = {"n": 0}

        def policy(obs):
            calls["n"] += 1
            return bad if calls["n"] == 6 else steering_policy(obs)

        t = tracker(policy)
        audit = Auditor(t)
        t.set_path(straight_path(np.zeros(N), np.full(N, 1.0), 8)[1:])
        statuses = [audit.step().status for _ in range(6)]
        assert statuses == [Status.TRACKING] * 5 + [Status.BRAKING]
        assert audit.outputs[-1].fault.startswith("policy returned")
        np.testing.assert_array_equal(audit.outputs[-1].action, 0.0)
        audit.run_until_stopped(40)
        assert audit.worst <= REL


@pytest.mark.parametrize("knots_frame,end_braking,end_stop", [("absolute", "at_end", "fastest"),
                                                              ("relative", "at_end", "fastest"),
                                                              ("relative", "predictive", "fastest"),
                                                              ("relative", "predictive", "end_knot")])
def test_observation_and_step_equal_the_environment(knots_frame, end_braking, end_stop):
    """The tracker feeds the policy the environment's observation and moves like env.step, to
    the stop at the end of the path (braking and stopping by the same rules)."""
    knots = straight_path(np.zeros(N), np.array([0.8, -0.5, 0.6, 0.4, -0.3, 0.2, 0.9]), 9)
    t = tracker(steering_policy, knots_frame=knots_frame, end_braking=end_braking, end_stop=end_stop)
    t.set_path(knots[1:])
    cfg = EnvConfig(dt=DT, n_next=N_NEXT, substeps=20, start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0,
                    adjustable=True, knots_frame=knots_frame, end_braking=end_braking, end_stop=end_stop)
    env = PathTrackingEnv(LIM, S.stack_paths([S.make_path(knots, t.max_knots)]), MAX_DIS, cfg)
    state = env.reset(jax.random.PRNGKey(0))
    np.testing.assert_allclose(t.observation(), np.asarray(state.obs), atol=1e-6)
    step = jax.jit(env.step)
    for _ in range(25):
        action = steering_policy(t.observation())
        state = step(state, jnp.asarray(action, jnp.float32))
        out = t.step()
        assert (out.status is not Status.TRACKING) == bool(state.pipeline_state.braking)
        if out.status is Status.STOPPED:
            break
        np.testing.assert_allclose(t.position, np.asarray(state.pipeline_state.p), atol=1e-6)
        np.testing.assert_allclose(t.s, float(state.pipeline_state.s), atol=1e-5)
        np.testing.assert_allclose(t.observation(), np.asarray(state.obs), atol=1e-5)


def test_drop_behind_keeps_the_reference_ahead():
    rng = np.random.default_rng(0)
    knots = np.cumsum(rng.uniform(-0.2, 0.2, (9, 3)), axis=0)
    path = S.make_path(knots, 12)
    s = 0.6 * float(path.length)
    shifted, s1 = S.drop_behind(path, jnp.asarray(s))
    assert int(shifted.n_knots) < int(path.n_knots)
    ahead = np.linspace(0.0, float(path.length) - s, 25)
    np.testing.assert_allclose(np.asarray(S.point_at(shifted, s1 + ahead)), np.asarray(S.point_at(path, s + ahead)),
                               atol=1e-5)
    assert float(shifted.length) == pytest.approx(float(path.length) - float(path.knot_s[
        int(S.knot_window(path, s, 0).index[0])]), abs=1e-5)
    w0, w1 = S.knot_window(path, s, 4), S.knot_window(shifted, s1, 4)
    np.testing.assert_allclose(np.asarray(w1.knots), np.asarray(w0.knots), atol=0)
    np.testing.assert_allclose(np.asarray(w1.knot_distances), np.asarray(w0.knot_distances), atol=1e-5)


def test_bad_construction_and_usage():
    ok = dict(controller_dt=1 / 200, max_knots=12, limits=LIM, dt=DT, n_next=N_NEXT, max_dis_between_knots=MAX_DIS)
    p0 = np.zeros(N)
    cases = [
        (dict(ok, controller_dt=0.03), "does not divide"),
        (dict(ok, controller_dt=0.2), "controller_dt"),
        (dict(ok, dt=None), "needs dt"),
        (dict(ok, limits=None), "needs limits"),
        (dict(ok, max_knots=2), "max_knots"),
        (dict(ok, path_joints=[0, 0, 1]), "path_joints"),
        (dict(ok, path_joints=[0, 9]), "path_joints"),
    ]
    for kwargs, match in cases:
        with pytest.raises(ValueError, match=match):
            OnlineTracker(steering_policy, p0, **kwargs)
    with pytest.raises(ValueError, match="callable"):
        OnlineTracker("not a policy", p0, **ok)
    with pytest.raises(ValueError, match="position must have shape"):
        OnlineTracker(steering_policy, np.zeros(6), **ok)
    with pytest.raises(ValueError, match="NaN"):
        OnlineTracker(steering_policy, np.full(N, np.nan), **ok)
    with pytest.raises(ValueError, match="outside the limits"):
        OnlineTracker(steering_policy, np.full(N, 3.5), **ok)
    with pytest.raises(ValueError, match="outside the limits"):
        OnlineTracker(steering_policy, p0, velocity=np.full(N, 5.0), **ok)
    t = OnlineTracker(steering_policy, p0, **ok)
    with pytest.raises(RuntimeError, match="set_path"):
        t.update_path(np.ones((2, N)))
    out = t.step()   # no path: holds at rest
    assert out.status is Status.STOPPED and out.fault == "no path set"
    np.testing.assert_array_equal(out.position, 0.0)
    with pytest.raises(PathError, match="leave the current position"):
        t.set_path(np.zeros((2, N)))
    with pytest.raises(PathError, match="at most 1 knot|max_knots"):
        OnlineTracker(steering_policy, p0, **dict(ok, max_knots=4)).set_path(np.cumsum(np.full((6, N), 0.1), 0))
    t.set_path(np.full((1, N), 0.5))
    t.step()
    with pytest.raises(RuntimeError, match="at rest"):
        t.set_path(np.full((1, N), 0.2))


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import networks as ppo_networks

    from mjx_pathtrack.deploy.export import export_policy, load_policy

    paths = S.stack_paths([S.make_path(straight_path(np.zeros(N), np.full(N, 0.5), 4), 8)] * 2)
    env = PathTrackingEnv(LIM, paths, MAX_DIS, EnvConfig(n_next=N_NEXT))
    nets = ppo_networks.make_ppo_networks(env.observation_size, env.action_size,
                                          preprocess_observations_fn=running_statistics.normalize,
                                          policy_hidden_layer_sizes=(16,), value_hidden_layer_sizes=(8,))
    key = jax.random.PRNGKey(1)
    normalizer = running_statistics.init_state(specs.Array((env.observation_size,), jnp.dtype("float32")))
    params = (normalizer, nets.policy_network.init(key))
    out = export_policy(tmp_path_factory.mktemp("export") / "policy", ppo_networks.make_inference_fn(nets), params,
                        env, "iiwa", iiwa.JOINT_NAMES)
    return load_policy(out)


def test_exported_policy_drives_the_tracker_within_limits(exported):
    t = OnlineTracker(exported, np.zeros(N), controller_dt=1 / 200, max_knots=12)
    assert t.dt == DT and t.substeps == 20 and t.observation_size == exported.observation_size
    assert exported.manifest["knots_frame"] == "absolute" and t.env.config.knots_frame == "absolute"
    assert exported.manifest["end_braking"] == "at_end" and t.env.config.end_braking == "at_end"
    np.testing.assert_array_equal(np.asarray(t.limits.jerk), np.asarray(LIM.jerk))
    audit = Auditor(t)
    t.set_path(straight_path(np.zeros(N), np.full(N, 0.8), 6)[1:])
    for _ in range(15):
        audit.step()
    assert audit.worst <= REL
    with pytest.raises(ValueError, match="manifest"):
        OnlineTracker(exported, np.zeros(N), controller_dt=0.01, dt=DT)


def readme_deploy_example() -> str:
    """The README's deployment snippet (the python block after **Deploy.**), verbatim."""
    text = (REPO / "README.md").read_text()
    block = text[text.index("**Deploy.**"):]
    return block[block.index("```python\n") + len("```python\n"):block.index("```", block.index("```python\n") + 3)]


def test_readme_deploy_example_runs_as_written_on_the_longest_committed_test_path(tmp_path):
    """The README example with an (untrained) iiwa export in place of ``runs/iiwa_mixed/export``
    on the committed iiwa random test path with the most knots (default ``max_knots``), then a
    changed path ahead; every setpoint within the limits."""
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import networks as ppo_networks

    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.deploy.export import export_policy
    from mjx_pathtrack.config.run import TrainConfig
    from mjx_pathtrack.rl.training import make_env

    env = make_env(TrainConfig(), "test")
    nets = ppo_networks.make_ppo_networks(env.observation_size, env.action_size,
                                          preprocess_observations_fn=running_statistics.normalize,
                                          policy_hidden_layer_sizes=(16,), value_hidden_layer_sizes=(8,))
    normalizer = running_statistics.init_state(specs.Array((env.observation_size,), jnp.dtype("float32")))
    params = (normalizer, nets.policy_network.init(jax.random.PRNGKey(0)))
    export_policy(tmp_path / "export", ppo_networks.make_inference_fn(nets), params, env, "iiwa", iiwa.JOINT_NAMES)

    code = readme_deploy_example()
    assert code.count('"runs/iiwa_mixed/export"') == 1
    knots = max(datasets.load_split("iiwa", "random", "test"), key=len)
    assert len(knots) > 64  # longer than the tracker's old default limit
    namespace = {"p0": knots[0], "knots": knots, "new_knots": knots[len(knots) // 2:][::-1]}
    exec(code.replace('"runs/iiwa_mixed/export"', repr(str(tmp_path / "export"))), namespace)
    out = namespace["out"]
    assert out.position.shape == (100, 7) and np.all(np.isfinite(out.position))
    tracker = namespace["tracker"]
    for _ in range(5):  # follows the changed path within every limit
        out = tracker.step()
        lim = tracker.limits
        for value, bound in ((out.position, None), (out.velocity, lim.vel), (out.acceleration, lim.acc)):
            if bound is None:
                assert np.all(value >= np.asarray(lim.pos_min) - 1e-6) and np.all(value <= np.asarray(lim.pos_max) + 1e-6)
            else:
                assert np.all(np.abs(value) <= np.asarray(bound) * (1 + 1e-5))


def test_set_and_update_path_reknot_what_they_are_given():
    """The tracker re-knots every path by its knot rule (here the papers' curvature rule capped at
    MAX_DIS): planner-dense waypoints on a curve become knots like the curve's own, the report
    says how far the two curves lie apart, an update continues the old path's direction, and the
    robot follows it to the end within every limit."""
    from mjx_pathtrack.core.knot_rule import KnotRule, reknot
    from mjx_pathtrack.core.spline_fit import fit_spline

    rule = KnotRule(max_spacing=MAX_DIS)
    t = tracker(steering_policy, controller_dt=1 / 100, max_knots=128, keep_knots=False)
    assert t.knot_rule == rule
    audit = Auditor(t)
    bend = np.array([[0.0] * N, [0.4, 0.3, -0.2, 0.5, 0.3, -0.4, 0.2], [0.9, 0.1, -0.5, 0.9, 0.6, -0.2, 0.7],
                     [1.2, -0.4, -0.3, 1.1, 0.2, 0.3, 1.0]])
    fit = fit_spline(bend)
    dense = fit.point_at(np.append(np.arange(0.0, fit.length, 0.03), fit.length))
    t.set_path(dense)
    native = reknot(bend, rule)
    n = int(t.path.n_knots)
    assert len(dense) > 3 * n and abs(n - len(native)) <= 2
    assert np.diff(np.asarray(t.path.knot_s)[:n]).max() <= MAX_DIS + 1e-5
    report = t.path_report
    assert report is not None and report.limit_shift == 0.0 and 0 < report.joint_distance < 0.02
    for _ in range(8):
        audit.step()
    tangent = np.asarray(S.tangent_at(t.path, t.s))
    detour = t.position + np.linspace(0.03, 0.9, 30)[:, None] * np.array([0.3, 0.5, 0.2, -0.4, 0.1, 0.3, -0.2])
    t.update_path(detour)
    assert t.path_report.knots.shape[0] < 20 and t.path_report.joint_distance < 0.02
    np.testing.assert_allclose(np.asarray(S.tangent_at(t.path, t.s + 1e-4)), tangent, atol=2e-2)
    end = audit.run_until_stopped()
    assert end.reached_end
    np.testing.assert_allclose(np.asarray(S.end_knot(t.path)), detour[-1], atol=1e-5)
    # the limits' allowance: a knot on the URDF limit is moved onto the model's
    t2 = tracker(steering_policy, controller_dt=1 / 100, max_knots=128, keep_knots=False)
    edge = straight_path(np.zeros(N), np.asarray(LIM.pos_max) + 0.02, 5)[1:]
    t2.set_path(edge)
    assert t2.path_report.limit_shift == pytest.approx(0.02, abs=1e-6)
    assert np.all(np.asarray(t2.path.knots) <= np.asarray(LIM.pos_max) + 1e-6)
