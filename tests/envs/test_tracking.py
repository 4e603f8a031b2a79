"""PathTrackingEnv: shapes, limits along rollouts, progress/deviation, braking, fresh resets."""

import dataclasses

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import limits as L
from mjx_pathtrack.core import reward as R
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv, normalize_position
from mjx_pathtrack.envs.wrappers import wrap_for_training
from path_fixtures import line_path, random_walk_paths

DT = 0.1


@pytest.fixture(scope="module")
def env():
    return PathTrackingEnv(iiwa.joint_limits(DT), random_walk_paths(), 0.5, EnvConfig())


def test_observation_layout_matches_reference_size(env):
    # docs/method.md §4: 3 n + n (N + 1) + 1 + 1 + N = 94 for the iiwa with N = 8
    assert env.observation_size == 94 and env.action_size == 7
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert state.obs.shape == (94,)
    assert bool(jnp.all(jnp.abs(state.obs) <= 1.0)) and bool(jnp.all(jnp.isfinite(state.obs)))
    # at rest: velocity and acceleration blocks are zero
    assert bool(jnp.all(state.obs[7:21] == 0.0))


def test_speed_limit_block_shows_the_speed_over_each_segments_fastest():
    """``observe_speed_limits``: ``n_next`` more entries after the papers' 94, each segment's
    ratio mapped from [0, 2] to [-1, 1]: the larger of ``|v| max_i(|u_i| / vel_i)`` (velocity
    limits along the chord ``u``) and ``|v| sqrt(max_i |q''_i| / acc_i)`` at the knot ending the
    segment (acceleration limits on the turn to the next chord); -1 at rest, 0 where the current
    speed puts the binding joint exactly at its limit; checked against a hand computation on an
    off-path state; a right-angle turn on a toy polyline gives the known ratio; zero-length
    segments beyond the end give 0."""
    from mjx_pathtrack.deploy.export import env_observation_layout
    from mjx_pathtrack.envs.tracking import segment_speed_ratios

    paths = random_walk_paths()
    lim = iiwa.joint_limits(DT)
    plain = PathTrackingEnv(lim, paths, 0.5, EnvConfig())
    env = PathTrackingEnv(lim, paths, 0.5, EnvConfig(observe_speed_limits=True))
    assert env.observation_size == 94 + 8
    state = jax.jit(env.reset)(jax.random.PRNGKey(3))
    np.testing.assert_array_equal(np.asarray(state.obs[:94]), np.asarray(jax.jit(plain.reset)(jax.random.PRNGKey(3)).obs))
    np.testing.assert_allclose(np.asarray(state.obs[94:]), -1.0)   # at rest
    track = state.pipeline_state
    v = 0.4 * np.asarray(lim.vel) * np.array([1, -1, 0.5, 0, 1, -0.2, 0.3])
    window = S.knot_window(env.reference(track), track.s, 8)
    knots = np.asarray(window.knots, np.float64)
    chords = np.diff(knots, axis=0)
    vel, acc, speed = np.asarray(lim.vel), np.asarray(lim.acc), np.linalg.norm(v)
    expect = [speed * np.max(np.abs(c) / np.linalg.norm(c) / vel) for c in chords]
    for k in range(len(chords) - 1):   # the turn at knot k + 1
        c0, c1 = chords[k], chords[k + 1]
        if np.linalg.norm(c0) > 1e-9 and np.linalg.norm(c1) > 1e-9:
            q2 = (c1 / np.linalg.norm(c1) - c0 / np.linalg.norm(c0)) / (0.5 * (np.linalg.norm(c0) + np.linalg.norm(c1)))
            expect[k] = max(expect[k], speed * np.sqrt(np.max(np.abs(q2) / acc)))
    obs = np.asarray(env.observe(track._replace(v=jnp.asarray(v, jnp.float32))))
    np.testing.assert_allclose(obs[94:], np.clip(-1 + np.array(expect), -1, 1), atol=1e-5)
    assert np.any(np.abs(obs[94:]) < 0.999)   # the check above is not all clipped
    # segments past the end knot have no length: ratio 0
    end = np.repeat(knots[-1:], 3, axis=0)
    np.testing.assert_array_equal(np.asarray(segment_speed_ratios(jnp.asarray(end), jnp.asarray(v), lim.vel, lim.acc)), 0.0)
    # a right angle after two 0.1 rad chords at 1 rad/s, limits 2 rad/s and 10 rad/s^2: the chords
    # allow 2 rad/s (ratio 0.5); the turn q'' = (0, 1) - (1, 0) over 0.1 rad allows 1 rad/s (ratio 1)
    toy = jnp.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [0.2, 0.1], [0.2, 0.1]])
    np.testing.assert_allclose(np.asarray(segment_speed_ratios(toy, jnp.array([1.0, 0.0]), jnp.array([2.0, 2.0]),
                                                               jnp.array([10.0, 10.0]))), [0.5, 1.0, 0.5, 0.0], atol=1e-6)
    assert env_observation_layout(env)[-1] == {"name": "speed_limits", "start": 94, "size": 8}


def test_deviation_block_shows_the_offset_from_the_reference_point():
    """``observe_deviation``: 7 more entries after the papers' 94, equal to (reference point at the
    current arc position - position) / 0.25 rad (clipped), the rest unchanged; the export's layout
    names the block before any task block."""
    from mjx_pathtrack.deploy.export import env_observation_layout
    from mjx_pathtrack.envs.tracking import DEVIATION_SCALE

    paths = random_walk_paths()
    plain = PathTrackingEnv(iiwa.joint_limits(DT), paths, 0.5, EnvConfig())
    env = PathTrackingEnv(iiwa.joint_limits(DT), paths, 0.5, EnvConfig(observe_deviation=True))
    assert env.observation_size == 94 + 7
    state = jax.jit(env.reset)(jax.random.PRNGKey(3))
    base = jax.jit(plain.reset)(jax.random.PRNGKey(3))
    np.testing.assert_array_equal(np.asarray(state.obs[:94]), np.asarray(base.obs))
    np.testing.assert_allclose(np.asarray(state.obs[94:]), 0.0, atol=1e-6)   # starts on the path
    # move the robot off the path by hand: the block shows the offset, scaled and clipped
    track = state.pipeline_state
    shift = jnp.array([0.05, -0.1, 0.0, 0.2, 0.0, 0.0, -0.5])
    moved = track._replace(p=track.p + shift)
    obs = np.asarray(env.observe(moved))
    np.testing.assert_allclose(obs[94:], np.clip(-np.asarray(shift) / DEVIATION_SCALE, -1, 1), atol=1e-5)
    layout = env_observation_layout(env)
    assert layout[-1] == {"name": "deviation", "start": 94, "size": 7}


def test_random_rollouts_keep_limits_and_finite_rewards(env):
    """Batched rollouts with random and extreme actions: the commanded state stays inside all
    limits at every step and inside every step (analytic extrema), rewards are finite."""
    wrapped = wrap_for_training(env, episode_length=200)
    batch, steps = 64, 120
    lim = env.limits
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(1), batch))

    @jax.jit
    def run(state, key):
        def body(state, k):
            k1, k2 = jax.random.split(k)
            random = jax.random.uniform(k1, (batch, 7), minval=-1.0, maxval=1.0)
            extreme = jnp.sign(jax.random.normal(k2, (batch, 7)))
            action = jnp.where(jnp.arange(batch)[:, None] < batch // 2, random, extreme)
            before = state.pipeline_state
            state = wrapped.step(state, action)
            after = state.pipeline_state
            fresh = state.done.astype(bool)
            ext = L.step_extrema(before.p, before.v, before.a, after.a, DT)
            return state, (ext, after.a, state.reward, fresh)

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    state, (ext, acc, rewards, fresh) = run(state, jax.random.PRNGKey(2))
    keep = ~fresh[..., None]  # steps that ended an episode were replaced by a reset
    tol = 1e-6
    pos_max, pos_min = np.asarray(lim.pos_max), np.asarray(lim.pos_min)
    assert np.all(np.where(keep, ext.p_max <= pos_max + tol * np.abs(pos_max), True))
    assert np.all(np.where(keep, ext.p_min >= pos_min - tol * np.abs(pos_min), True))
    assert np.all(np.where(keep, np.maximum(ext.v_max, -ext.v_min) <= np.asarray(lim.vel) * (1 + tol), True))
    assert np.all(np.abs(acc) <= np.asarray(lim.acc) * (1 + tol))
    assert np.all(np.where(keep, ext.jerk_abs <= np.asarray(lim.jerk) * (1 + 1e-5), True))
    assert np.all(np.isfinite(rewards))
    assert int(fresh.sum()) > 0  # episodes did end (and were reset) during the rollout


def test_following_a_straight_path_has_tiny_deviation_and_progress():
    cfg = EnvConfig(start_range=(0.0, 0.0), min_fraction=1.0, terminate_deviation=None)
    env = PathTrackingEnv(iiwa.joint_limits(DT), line_path(1.0), 0.2, cfg)
    state = env.reset(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    action = jnp.zeros(7).at[0].set(1.0)  # joint 0 as fast as allowed, others held (mid-range = 0)
    d_max, total = [], 0.0
    while not bool(state.pipeline_state.braking):
        state = step(state, action)
        if not bool(state.metrics["reached_end"]):  # (beyond the end the reference is the end knot)
            d_max.append(float(state.metrics["d_max"]))
            total += float(state.metrics["length"])
            assert float(state.pipeline_state.s) == pytest.approx(total, abs=1e-5)
    assert len(d_max) >= 3 and max(d_max) < 1e-4
    # overshooting the end is measured against the end knot
    state = step(state, action)
    assert float(state.metrics["d_max"]) == pytest.approx(float(state.pipeline_state.p[0]) - 1.0, abs=1e-4)


def test_braking_at_end_stops_and_counts_the_remaining_steps():
    cfg = EnvConfig(start_range=(0.0, 0.0), min_fraction=1.0, terminate_deviation=None)
    env = PathTrackingEnv(iiwa.joint_limits(DT), line_path(0.6), 0.2, cfg)
    state = env.reset(jax.random.PRNGKey(0))
    max_steps = int(state.pipeline_state.max_steps)
    step = jax.jit(env.step)
    action = jnp.zeros(7).at[0].set(1.0)
    for i in range(max_steps):
        state = step(state, action)
        if state.done:
            break
    track = state.pipeline_state
    assert bool(state.done) and i + 1 < max_steps  # stopped before the time budget ran out
    assert float(jnp.max(jnp.abs(track.v))) < 0.01 and float(jnp.max(jnp.abs(track.a))) < 0.01
    # success: stopped with the last point within 0.05 rad of the end knot
    final_dev = abs(float(track.p[0]) - 0.6)
    assert float(state.metrics["success"]) == float(final_dev < 0.05)
    # the stop reward is the per-step reward times the remaining steps
    per_step = sum(float(v) for k, v in state.metrics.items() if k.startswith("reward/"))
    assert float(state.reward) == pytest.approx(per_step * (max_steps + 1 - (i + 1)), rel=1e-5)
    # full speed to the end overshoots it by the braking distance, which is then measured
    assert 0.6 < float(track.p[0]) < 0.6 + 0.5 * float(env.limits.vel[0]) ** 2 / float(env.limits.acc[0]) + 0.2


def test_fresh_resets_draw_new_episodes_and_runs_are_reproducible(env):
    wrapped = wrap_for_training(env, episode_length=3)
    batch = 16

    def run(seed):
        state = wrapped.reset(jax.random.split(jax.random.PRNGKey(seed), batch))
        starts = [np.asarray(state.pipeline_state.s)]
        step = jax.jit(wrapped.step)
        for _ in range(6):
            state = step(state, jnp.zeros((batch, 7)))
            starts.append(np.asarray(state.pipeline_state.s))
        return np.stack(starts), np.asarray(state.obs)

    s1, obs1 = run(3)
    s2, obs2 = run(3)
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(obs1, obs2)
    # episode length 3: slots were reset at steps 3 and 6 with newly drawn start positions
    assert not np.allclose(s1[3], s1[0]) and not np.allclose(s1[6], s1[3])


def test_jerk_reward_marks_chatter():
    # R_jerk (weight 1): bang-bang chatter (+1, -1, ...) changes every acceleration at about the
    # jerk limit and earns almost nothing; a steady action earns nearly the full weight once its
    # acceleration is reached; the papers' weight 0 leaves the reward unchanged
    cfg = EnvConfig(reward=dataclasses.replace(R.RewardWeights(), jerk=1.0))
    env = PathTrackingEnv(iiwa.joint_limits(DT), random_walk_paths(), 0.5, cfg)
    plain = PathTrackingEnv(iiwa.joint_limits(DT), random_walk_paths(), 0.5, EnvConfig())
    steps = 8

    def run(env, actions):
        def body(s, a):
            s = env.step(s, a)
            return s, (s.metrics["reward/jerk"], s.reward)
        return jax.lax.scan(body, env.reset(jax.random.PRNGKey(3)), actions)[1]

    signs = jnp.where(jnp.arange(steps) % 2 == 0, 1.0, -1.0)[:, None] * jnp.ones((steps, 7))
    chatter, _ = jax.jit(lambda a: run(env, a))(signs)
    steady, reward = jax.jit(lambda a: run(env, a))(jnp.full((steps, 7), 0.2))
    _, plain_reward = jax.jit(lambda a: run(plain, a))(jnp.full((steps, 7), 0.2))
    assert float(jnp.max(chatter[2:])) < 0.1, chatter
    assert float(jnp.min(steady[-3:])) > 0.9, steady
    np.testing.assert_allclose(np.asarray(reward - steady), np.asarray(plain_reward), rtol=1e-5, atol=1e-5)


def test_normalize_position_wraps_continuous_joints():
    lo = jnp.array([-1.0, -jnp.inf])
    hi = jnp.array([1.0, jnp.inf])
    out = normalize_position(jnp.array([0.5, jnp.pi / 2]), lo, hi)
    np.testing.assert_allclose(np.asarray(out), [0.5, 0.5], atol=1e-6)
    # the same under jit with traced limits, and with known all-finite limits (no wrapped branch)
    traced = jax.jit(normalize_position)(jnp.array([0.5, jnp.pi / 2]), lo, hi)
    np.testing.assert_array_equal(traced, out)
    p = jnp.array([[0.5, -2.0], [-1.0, 3.0]])
    finite_lo, finite_hi = jnp.array([-1.0, -2.0]), jnp.array([1.0, 3.0])
    np.testing.assert_array_equal(normalize_position(p, finite_lo, finite_hi),
                                  jax.jit(normalize_position)(p, finite_lo, finite_hi))
    np.testing.assert_allclose(normalize_position(p, finite_lo, finite_hi), [[0.5, -1.0], [-1.0, 1.0]])


def test_relative_knots_show_knot_minus_position_and_keep_the_rest():
    """knots_frame="relative": the knot block is (knot - p) / (N max_dis), clipped to [-1, 1];
    every other block equals the papers' absolute observation of the same state."""
    from mjx_pathtrack.core import spline as S

    paths = random_walk_paths()
    absolute = PathTrackingEnv(iiwa.joint_limits(DT), paths, 0.5, EnvConfig())
    relative = PathTrackingEnv(iiwa.joint_limits(DT), paths, 0.5, EnvConfig(knots_frame="relative"))
    assert relative.observation_size == absolute.observation_size
    state = relative.reset(jax.random.PRNGKey(3))
    step = jax.jit(relative.step)
    for i in range(4):  # move off the path start so that p and the knots differ
        state = step(state, jax.random.uniform(jax.random.PRNGKey(i), (7,), minval=-1.0, maxval=1.0))
    track = state.pipeline_state
    window = S.knot_window(relative.episode_path(track), track.s, 8)
    expected = np.clip((np.asarray(window.knots) - np.asarray(track.p)) / (8 * 0.5), -1.0, 1.0).reshape(-1)
    obs_rel, obs_abs = np.asarray(relative.observe(track)), np.asarray(absolute.observe(track))
    block = slice(21, 21 + 7 * 9)
    np.testing.assert_allclose(obs_rel[block], expected, atol=1e-6)
    assert np.max(np.abs(expected)) > 1e-3  # the state is off the knots: a real check
    np.testing.assert_array_equal(np.delete(obs_rel, np.r_[block]), np.delete(obs_abs, np.r_[block]))
    with pytest.raises(ValueError, match="knots_frame"):
        EnvConfig(knots_frame="polar")


def test_end_tolerance_starts_braking_before_the_end():
    """EnvConfig.end_tolerance: within that arc length of the path end the end counts as reached
    (braking, metric reached_end); 0 keeps the papers' rule (only at the end)."""
    paths = random_walk_paths(n_paths=2)
    actions = jnp.ones(7) * 0.3
    for tolerance, expected in ((0.0, False), (1e3, True)):
        env = PathTrackingEnv(iiwa.joint_limits(DT), paths, 0.5, EnvConfig(end_tolerance=tolerance))
        state = env.step(env.reset(jax.random.PRNGKey(0)), actions)
        assert bool(state.pipeline_state.braking) is expected
        assert float(state.metrics["reached_end"]) == float(expected)
        assert float(state.pipeline_state.s) < float(env.episode_path(state.pipeline_state).length)  # not at the end
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="end_tolerance"):
            EnvConfig(end_tolerance=bad)


def _run_to_stop(env, action):
    state = env.reset(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    for _ in range(int(state.pipeline_state.max_steps)):
        state = step(state, action)
        if state.done:
            break
    return state


def test_predictive_braking_stops_at_the_end_instead_of_overshooting_it():
    """EnvConfig.end_braking="predictive": full speed along a straight path, braking starts when
    the fastest stop reaches the end, and the robot comes to rest at the end knot (within the
    position covered by one decision step at the last speed); the papers' rule overshoots by the
    braking distance. The stop is never later, and ends stopped (done, at rest)."""
    action = jnp.zeros(7).at[0].set(1.0)
    final = {}
    for rule in ("at_end", "predictive"):
        cfg = EnvConfig(start_range=(0.0, 0.0), min_fraction=1.0, terminate_deviation=None, end_braking=rule)
        env = PathTrackingEnv(iiwa.joint_limits(DT), line_path(2.0), 0.5, cfg)
        state = _run_to_stop(env, action)
        track = state.pipeline_state
        assert bool(state.done) and float(jnp.max(jnp.abs(track.v))) < 0.01
        final[rule] = (float(track.p[0]), int(track.steps))
    v, A = float(iiwa.joint_limits(DT).vel[0]), float(iiwa.joint_limits(DT).acc[0])
    assert final["at_end"][0] - 2.0 > 0.5 * v ** 2 / A * 0.8  # overshoot ~ the braking distance
    assert abs(final["predictive"][0] - 2.0) < v * DT  # stops at the end, up to one step's travel
    assert abs(final["predictive"][0] - 2.0) < 0.5 * (final["at_end"][0] - 2.0)
    assert final["predictive"][1] <= final["at_end"][1]
    with pytest.raises(ValueError, match="end_braking"):
        EnvConfig(end_braking="late")


def test_stop_length_is_the_length_of_the_braking_that_follows(env):
    """PathTrackingEnv.stop_length of a moving state (away from position limits) equals the
    path-joint length of the braking the environment then executes, decision step by decision
    step, and that braking ends at rest within ``stop_steps``."""
    lim = env.limits
    key = jax.random.PRNGKey(3)
    p = jnp.zeros(7)
    v = 0.9 * lim.vel * jax.random.uniform(key, (7,), minval=-1.0, maxval=1.0)
    a = jnp.zeros(7)
    predicted = float(jax.jit(env.stop_length)(p, v, a))
    total = 0.0
    for _ in range(env.stop_steps):
        a1 = L.braking_acceleration(lim, p, v, a, DT)
        p1, v, _ = L.integrate(p, v, a, a1, DT, DT)
        total += float(jnp.linalg.norm(p1 - p))
        p, a = p1, a1
    assert float(jnp.max(jnp.abs(v))) < 1e-4 and float(jnp.max(jnp.abs(a))) < 1e-3
    assert predicted == pytest.approx(total, rel=1e-5)
    assert predicted > 0.1


def test_bad_construction_errors():
    paths = random_walk_paths(n_paths=2)
    with pytest.raises(ValueError, match="path joints"):
        PathTrackingEnv(iiwa.joint_limits(DT), paths, 0.5, path_joints=[0, 1, 2])
    with pytest.raises(ValueError, match="max_dis_between_knots"):
        PathTrackingEnv(iiwa.joint_limits(DT), paths, float("nan"))


def test_path_replaced_mid_episode_continues_within_limits():
    """Paper Fig. 4: the reference ahead changes during motion; the robot continues from where it
    is, sees the new knots at once and keeps every limit (checked inside each step)."""
    cfg = EnvConfig(adjustable=True, terminate_deviation=None, start_range=(0.0, 0.2))
    env = PathTrackingEnv(iiwa.joint_limits(DT), random_walk_paths(n_paths=3), 0.5, cfg)
    batch = 8
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(4), batch))
    step = jax.jit(jax.vmap(env.step))
    lim = env.limits
    rng = np.random.default_rng(0)
    worst = 0.0

    def run(state, n):
        nonlocal worst
        for _ in range(n):
            action = jnp.asarray(rng.uniform(-1, 1, (batch, 7)), jnp.float32)
            before = state.pipeline_state
            state = step(state, action)
            after = state.pipeline_state
            ext = L.step_extrema(before.p, before.v, before.a, after.a, DT)
            over = max(float(jnp.max(ext.p_max - lim.pos_max)), float(jnp.max(lim.pos_min - ext.p_min)))
            vel = float(jnp.max(jnp.maximum(ext.v_max, -ext.v_min) / lim.vel))
            worst = max(worst, over, vel - 1.0, float(jnp.max(ext.jerk_abs / lim.jerk)) - 1.0)
            assert bool(jnp.all(jnp.isfinite(state.obs)))
        return state

    state = run(state, 10)
    s_before = np.asarray(state.pipeline_state.s)
    detour = np.clip(np.asarray(state.pipeline_state.p)[:, None, :] + np.linspace(0.1, 1.0, 10)[None, :, None]
                     * np.array([0.5, -0.3, 0.4, 0.2, -0.5, 0.3, 0.1]), -0.9 * iiwa.POS, 0.9 * iiwa.POS)
    new = jax.jit(jax.vmap(env.replace_reference))(state, jnp.asarray(detour, jnp.float32))
    np.testing.assert_array_equal(np.asarray(new.pipeline_state.s), s_before)
    # the next knot shown is the first new knot (the knot at s is the cut point q(s))
    first_shown = np.asarray(new.obs)[:, 21 + 7:21 + 14]
    expected = np.asarray(normalize_position(jnp.asarray(detour[:, 0]), lim.pos_min, lim.pos_max))
    np.testing.assert_allclose(first_shown, expected, atol=1e-5)
    run(new, 30)
    assert worst <= 1e-6
    with pytest.raises(ValueError, match="adjustable"):
        plain = PathTrackingEnv(iiwa.joint_limits(DT), random_walk_paths(n_paths=1), 0.5)
        plain.replace_reference(plain.reset(jax.random.PRNGKey(0)), jnp.zeros((3, 7)))


def test_a_dense_detour_is_reknotted_before_it_replaces_the_path_ahead():
    """env.user_knots re-places a planner's dense waypoints by the env's knot rule (default: the
    papers' curvature rule capped at max_dis 0.5) for replace_reference, jitted and batched: the
    observation then shows the re-knotted knots, which lie on the dense curve."""
    from mjx_pathtrack.core.knot_rule import KnotRule, curve_distance

    cfg = EnvConfig(adjustable=True, terminate_deviation=None, start_range=(0.0, 0.2))
    env = PathTrackingEnv(iiwa.joint_limits(DT), random_walk_paths(n_paths=3), 0.5, cfg)
    assert env.knot_rule == KnotRule(max_spacing=0.5)
    batch = 4
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(1), batch))
    track = state.pipeline_state
    tangent = np.asarray(jax.vmap(lambda t: S.tangent_at(env.reference(t), t.s))(track))
    here = np.asarray(jax.vmap(lambda t: S.point_at(env.reference(t), t.s))(track))
    direction = np.array([0.5, -0.3, 0.4, 0.2, -0.5, 0.3, 0.1])
    new = []
    for b in range(batch):
        dense = here[b] + np.linspace(0.03, 1.2, 40)[:, None] * direction + np.sin(np.linspace(0, 3, 40))[:, None] * 0.2
        k = env.user_knots(np.concatenate([here[b][None], dense]), start_slope=tangent[b])
        assert len(k) < len(dense) / 2 and curve_distance(np.concatenate([here[b][None], dense]), k, start_slope=tangent[b])[0] < 0.05
        new.append(k[1:])
    count = np.array([len(k) for k in new])
    padded = np.stack([np.concatenate([k, np.repeat(k[-1:], count.max() - len(k), 0)]) for k in new])
    out = jax.jit(jax.vmap(env.replace_reference))(state, jnp.asarray(padded, jnp.float32), jnp.asarray(count))
    path = out.pipeline_state.path
    for b in range(batch):   # the reference ahead ends with exactly the re-knotted knots
        n = int(path.n_knots[b])
        np.testing.assert_allclose(np.asarray(path.knots[b, n - count[b]:n]), new[b], atol=1e-6)
    # and the observation shows them: every re-knotted knot within the window appears in it
    shown = np.asarray(out.obs)[:, 21:21 + 9 * 7].reshape(batch, 9, 7)
    first = np.asarray(normalize_position(jnp.asarray(padded[:, 0], jnp.float32), env.limits.pos_min,
                                          env.limits.pos_max))
    assert np.all(np.min(np.abs(shown - first[:, None]).max(-1), axis=1) < 1e-5)


def _stop_rollout(dt: float, end_stop: str, jerk_factor: float = 1.0, batch: int = 48, tolerance: float = 0.05):
    """Short sub-paths driven by random (first half) and bang-bang (second half) actions until
    every episode is done, batched and jitted as in training (the package's rollout engine).
    Returns per episode: done by the stop at the end, the final state, the end knot, and the
    largest in-step |x| / limit over every live step (position, velocity, acceleration, jerk)."""
    from mjx_pathtrack.core import spline as S
    from mjx_pathtrack.envs.episodes import run_episodes
    from mjx_pathtrack.evaluation.rollout import limit_ratios

    cfg = EnvConfig(dt=dt, substeps=max(int(round(dt / 0.1 * 24)), 1), start_range=(0.85, 0.9), min_fraction=0.05,
                    max_fraction=0.1, terminate_deviation=None, end_braking="predictive", end_stop=end_stop,
                    end_knot_tolerance=tolerance, duration=200.0)
    env = PathTrackingEnv(iiwa.joint_limits(dt, jerk_factor), random_walk_paths(), 0.5, cfg)
    steps = int(round(12.0 / dt))

    def policy(obs, key):
        k1, k2 = jax.random.split(key)
        random = jax.random.uniform(k1, (batch, 7), minval=-1.0, maxval=1.0)
        extreme = jnp.sign(jax.random.normal(k2, (batch, 7)))
        return jnp.where(jnp.arange(batch)[:, None] < batch // 2, random, extreme)

    def accumulate(acc, before, after, live, _):
        ratio = limit_ratios(env.limits, before.pipeline_state.p, before.pipeline_state.v, before.pipeline_state.a,
                             after.pipeline_state.a, dt)
        stopped = live & (after.done > 0) & (after.metrics["reached_end"] > 0)
        return jnp.maximum(acc[0], jnp.where(live[:, None, None], ratio, 0.0)), acc[1] | stopped

    @jax.jit
    def run(key):
        k_reset, k_run = jax.random.split(key)
        state = jax.vmap(env.reset)(jax.random.split(k_reset, batch))
        init = (jnp.zeros((batch, 4, 7)), jnp.zeros(batch, bool))
        final, _ = run_episodes(jax.vmap(env.step), policy, state, jax.random.split(k_run, steps), accumulate, init)
        track = final.state.pipeline_state
        ends = jax.vmap(lambda t: S.end_knot(env.episode_path(t)))(track)
        return final.acc, final.done, track, ends

    (worst, stopped), done, track, ends = jax.device_get(run(jax.random.PRNGKey(5)))
    return stopped & done, track, ends, worst


@pytest.mark.slow
@pytest.mark.parametrize("dt, jerk_factor", [(0.1, 1.0), (0.05, 1.0), (0.1, 0.25), (0.4, 1.0)])
def test_end_knot_stop_rests_at_the_end_knot_within_every_limit(dt, jerk_factor):
    """EnvConfig.end_stop="end_knot" after random and bang-bang motion, at short and long dt and
    with a binding jerk limit: every limit holds at every instant of every step (braking phase
    included), every episode stops at the end, and there every joint rests within the tolerance
    of its end-knot coordinate; the papers' fastest stop ends farther away."""
    tol = 0.05
    stopped, track, ends, worst = _stop_rollout(dt, "end_knot", jerk_factor, tolerance=tol)
    assert np.all(worst <= 1.0 + 1e-6), f"limit ratios up to {worst.max(axis=(0, 2))} (pos, vel, acc, jerk)"
    assert stopped.all(), f"{int((~stopped).sum())} of {len(stopped)} episodes did not stop at the end"
    assert np.all(np.abs(track.v) < 0.01) and np.all(np.abs(track.a) < 0.01)
    miss = np.abs(track.p - ends)
    assert miss.max() <= tol + 1e-3, f"a joint rests {miss.max():.4f} rad from its end-knot coordinate"
    fastest_stopped, fastest_track, fastest_ends, fastest_worst = _stop_rollout(dt, "fastest", jerk_factor)
    assert np.all(fastest_worst <= 1.0 + 1e-6)
    fastest_miss = np.linalg.norm(fastest_track.p - fastest_ends, axis=-1)[fastest_stopped]
    assert np.mean(np.linalg.norm(miss, axis=-1)) < 0.5 * np.mean(fastest_miss)


def test_end_knot_stop_gives_way_to_the_fastest_stop_and_rejects_bad_settings():
    """``transition(..., fastest_stop=True)`` (the online tracker's faults) brakes every joint as
    fast as it can even with end_stop="end_knot"; bad settings are refused by name."""
    paths = random_walk_paths(n_paths=2)
    lim = iiwa.joint_limits(DT)
    knot = PathTrackingEnv(lim, paths, 0.5, EnvConfig(end_stop="end_knot", terminate_deviation=None))
    fast = PathTrackingEnv(lim, paths, 0.5, EnvConfig(end_stop="fastest", terminate_deviation=None))
    track = knot.reset(jax.random.PRNGKey(0)).pipeline_state
    moving = track._replace(v=0.5 * lim.vel * jnp.array([1, -1, 1, -1, 1, -1, 1.0]), braking=jnp.ones((), bool))
    a_fast = fast.transition(moving, jnp.zeros(7))[0].a
    a_fault = knot.transition(moving, jnp.zeros(7), fastest_stop=True)[0].a
    a_knot = knot.transition(moving, jnp.zeros(7))[0].a
    assert np.array_equal(np.asarray(a_fault), np.asarray(a_fast))
    assert not np.array_equal(np.asarray(a_knot), np.asarray(a_fast))  # (the end knot is not where the stop ends)
    with pytest.raises(ValueError, match="end_stop"):
        EnvConfig(end_stop="soon")
    with pytest.raises(ValueError, match="end_knot_tolerance"):
        EnvConfig(end_knot_tolerance=0.0)
