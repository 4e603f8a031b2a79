"""ARMAR-4 balance task: standing still keeps it upright, a push makes it fall and ends the
episode, observation sizes of docs/method.md §4. One jitted rollout (MJX with contacts compiles
slowly) serves the physics tests."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mjx_pathtrack.deploy.export import observation_layout

from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs.tracking import EnvConfig
from mjx_pathtrack.robots.registry import load_robot
from mjx_pathtrack.envs.tasks import humanoid_balance as H
from mjx_pathtrack.config.run import TrainConfig

STEPS = 12  # decision steps of the rollout (1.2 s)
PUSH = 2.5  # roll rate [rad/s] given to the pelvis of the pushed robot


@pytest.fixture(scope="module")
def robot():
    """The fixed-legs task's robot (legs welded) at the task's physics rate (80 Hz)."""
    return load_robot(H.STANDING_ROBOT, sim_dt=0.1 / H.PHYSICS_SUBSTEPS)


@pytest.fixture(scope="module")
def legs_robot():
    """The robot with leg joints (controlled legs, or fixed legs held by their servos)."""
    return load_robot(H.ROBOT)


def small_paths(robot, n_paths=2, n_knots=5, seed=0):
    """Short upper-body paths around the initial pose (inside the limits)."""
    upper = np.flatnonzero(robot.path_mask)
    lo, hi = np.asarray(robot.limits.pos_min)[upper], np.asarray(robot.limits.pos_max)[upper]
    start = np.clip(np.asarray(robot.q0)[upper], lo + 0.1, hi - 0.1)  # inside: zero action holds still
    rng = np.random.default_rng(seed)
    fits = [S.fit_spline(np.clip(start + np.cumsum(rng.uniform(-0.05, 0.05, (n_knots, len(upper))), 0), lo, hi))
            for _ in range(n_paths)]
    return S.stack_fits(fits)


def make(robot, legs="fixed", base_sensor=True, duration=STEPS * 0.1):
    cfg = EnvConfig(duration=duration, start_range=(0.0, 0.0), min_fraction=1.0, reward=H.BALANCE_WEIGHTS,
                    substeps=robot.n_substeps)
    return H.HumanoidBalanceEnv(robot, small_paths(robot), 0.2, cfg, H.BalanceOptions(legs=legs, base_sensor=base_sensor))


@pytest.fixture(scope="module")
def rollout(robot):
    """Two fixed-leg robots holding still (zero action: zero acceleration from rest) for one
    episode; the second gets a sideways push (pelvis roll rate) at the start."""
    env = make(robot)

    @jax.jit
    def run(keys, roll_rate):
        state = jax.vmap(env.reset)(keys)
        data = state.pipeline_state.executor
        data = data.replace(qvel=data.qvel.at[:, 3].set(roll_rate))
        state = state.replace(pipeline_state=state.pipeline_state._replace(executor=data))
        action = jnp.zeros((keys.shape[0], env.action_size))

        def body(state, _):
            nxt = jax.vmap(env.step)(state, action)
            return nxt, (nxt.done, nxt.metrics["task_failed"], nxt.metrics["tilt"], nxt.reward, nxt.obs,
                         nxt.metrics["reward/tilt"])

        return state.obs, jax.lax.scan(body, state, None, length=STEPS)[1]

    obs0, out = run(jax.random.split(jax.random.PRNGKey(0), 2), jnp.array([0.0, PUSH]))
    return env, np.asarray(obs0), [np.asarray(x) for x in out]


def test_holding_still_stays_upright_for_the_episode(rollout):
    env, obs0, (done, failed, tilt, reward, obs, tilt_reward) = rollout
    steps = int(np.argmax(done[:, 0])) + 1
    assert done[:, 0].any() and steps >= STEPS - 1  # the episode ran out its time budget ...
    assert failed[:steps, 0].max() == 0  # ... without falling
    assert tilt[:steps, 0].max() < 0.01, tilt[:, 0]
    assert np.all(np.isfinite(reward[:steps, 0]))
    assert tilt_reward[:steps, 0].min() > 0.8 * H.BALANCE_WEIGHTS.tilt  # the tilt term sees an upright robot
    # pelvis observation: at the start exactly, then nearly, at rest and upright
    base = obs0[0, -H.BASE_OBS_SIZE:]
    np.testing.assert_allclose(base[:3], 0.0, atol=1e-5)
    np.testing.assert_allclose(base[3:7], [1, 0, 0, 0], atol=1e-5)
    assert base[7] == pytest.approx(-1.0, abs=1e-3)
    assert np.abs(obs[steps - 1, 0, -H.BASE_OBS_SIZE:][4:7]).max() < 0.01


def test_push_makes_it_fall_and_ends_the_episode(rollout):
    env, _, (done, failed, tilt, reward, obs, tilt_reward) = rollout
    assert done[:, 1].any()
    step = int(np.argmax(done[:, 1]))
    assert step < STEPS - 2  # well before the time budget
    assert failed[step, 1] == 1 and tilt[step, 1] > H.FALL_TILT
    assert failed[:step, 1].max() == 0 and tilt[0, 1] < H.FALL_TILT  # it fell during the rollout
    assert tilt_reward[step, 1] == 0.0  # beyond 0.125 rad the tilt term is 0


def test_observation_sizes_match_reference(robot, legs_robot, rollout):
    env, obs0, (_, _, _, _, obs, _) = rollout
    assert (env.observation_size, env.action_size) == (234, 18)
    assert obs0.shape == (2, 234) and obs.shape[-1] == 234 and np.abs(obs).max() <= 1.0
    key = jax.random.PRNGKey(0)
    for which, legs, sensor, size, actions in ((robot, "fixed", False, 226, 18), (legs_robot, "fixed", True, 234, 18),
                                               (legs_robot, "controlled", True, 270, 30)):
        other = make(which, legs, sensor)
        assert (other.observation_size, other.action_size) == (size, actions)
        assert jax.eval_shape(other.reset, key).obs.shape == (size,)
        layout = observation_layout(other.limits.n_joints, len(other.path_joints), 8,
                                    other.extra_observation_blocks())
        assert sum(b["size"] for b in layout) == size and other.task_name == "balance"


def _stand(robot, q, seconds=2.0) -> float:
    """Largest pelvis tilt [rad] of ``robot`` standing with its servos holding ``q`` (C MuJoCo)."""
    import mujoco

    model, data = robot.mj_model, mujoco.MjData(robot.mj_model)
    data.qpos[:] = np.asarray(robot.qpos(q))
    data.ctrl[:] = np.asarray(robot.ctrl(q, np.zeros_like(q)))
    base, tilt = model.body("base").id, 0.0
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)
        tilt = max(tilt, float(np.arccos(np.clip(data.xmat[base].reshape(3, 3)[2, 2], -1.0, 1.0))))
    return tilt


def test_controlled_legs_start_inside_their_limits_standing_on_flat_soles(legs_robot):
    """ARMAR-4's knees have q0 = 0, 0.035 rad below their lower limit: joints outside the path
    start HOME_MARGIN inside their limits (the safe action space needs them inside, and a hold
    still away from the one-sided range at a limit), the knees bent by as much and the ankles'
    pitch turned back by as much, so that the soles stay flat and the robot stands still; the
    knees moved alone tilt the soles and the robot tips over."""
    import mujoco

    env = make(legs_robot, "controlled")
    legs = np.flatnonzero(~np.asarray(legs_robot.path_mask))
    lo, hi = np.asarray(env.limits.pos_min)[legs], np.asarray(env.limits.pos_max)[legs]
    q0, home = np.asarray(legs_robot.q0), np.asarray(env.home)
    assert (q0[legs] < lo).any()  # the case this is about
    names = list(legs_robot.joint_names)
    margin = np.where(["ank2" in names[j] for j in legs], 0.025, 0.1)  # the ankle roll's range is +-0.025 rad
    assert ((home[legs] >= lo + margin - 1e-6) & (home[legs] <= hi - margin + 1e-6)).all()
    # the knees 0.1 rad above their lower limit, each ankle pitch turned by its knee's change
    # (antiparallel axes), every other leg joint at q0 (0, the middle of the ankle roll's
    # +-0.025 rad)
    expected = np.asarray(q0, np.float64).copy()
    for side in ("r0", "r1"):
        knee, ankle = names.index(f"leg_knee_joint_{side}"), names.index(f"leg_ank1_joint_{side}")
        expected[knee] = float(env.limits.pos_min[knee]) + 0.1
        expected[ankle] += expected[knee] - q0[knee]
    np.testing.assert_allclose(home[legs], expected[legs], atol=1e-6)
    model, data = legs_robot.mj_model, mujoco.MjData(legs_robot.mj_model)

    def soles(q):
        data.qpos[:] = np.asarray(legs_robot.qpos(q))
        mujoco.mj_kinematics(model, data)
        return np.stack([data.xmat[model.body(f"leg_ank2_r{i}").id] for i in (0, 1)])

    np.testing.assert_allclose(soles(home), soles(q0), atol=1e-6)
    knees_only = np.clip(q0, np.asarray(env.limits.pos_min), np.asarray(env.limits.pos_max))
    assert np.abs(soles(knees_only) - soles(q0)).max() > 0.03
    assert _stand(legs_robot, home) < 0.01
    assert _stand(legs_robot, knees_only) > 0.3
    # at rest at home every leg joint can accelerate both ways, so holding still is an inner
    # action; at the limit (knees_only) a knee's range is one-sided and holding still is -1
    from mjx_pathtrack.core import limits as L

    def accel_range(q):
        z = jnp.zeros_like(env.home)
        return [np.asarray(x)[legs] for x in L.safe_acceleration_range(env.limits, jnp.asarray(q, jnp.float32), z, z,
                                                                      env.config.dt)[:2]]

    a_min, a_max = accel_range(home)
    assert (a_min < 0).all() and (a_max > 0).all(), (a_min, a_max)
    a_min, a_max = accel_range(knees_only)
    knees = np.array(["knee" in names[j] for j in legs])
    assert (a_min[knees] > -1e-3).all() and (a_min[~knees] < -1.0).all() and (a_max > 0).all(), (a_min, a_max)


def test_bad_options_are_rejected(robot):
    with pytest.raises(ValueError, match="legs must be one of"):
        make(robot, legs="hopping")
    with pytest.raises(ValueError, match="no floating base"):
        H.HumanoidBalanceEnv(load_robot("armar4"), small_paths(robot), 0.2, EnvConfig())
    with pytest.raises(ValueError, match="no leg joints to control"):
        make(robot, legs="controlled")


@pytest.mark.parametrize("legs,robot_name", [("fixed", H.STANDING_ROBOT), ("controlled", H.ROBOT)])
def test_training_env_uses_welded_legs_when_they_are_fixed(legs, robot_name):
    cfg = TrainConfig().replace(task="balance", robot="armar4", executor="mjx", legs=legs)
    env = H.make_env(cfg, "test")
    assert env.robot.name == robot_name and env.action_size == (18 if legs == "fixed" else 30)
    assert env.robot.mj_model.opt.timestep == pytest.approx(1 / 240)  # the config's 24 sub-steps: 240 Hz


def test_training_env_runs_its_physics_at_the_configs_substeps():
    """``--substeps`` is the physics rate (the task's preset: 8, i.e. 80 Hz); the servos soften
    with the coarser step (bandwidth x sim_dt constant) and the executor takes as many steps."""
    cfg = TrainConfig().replace(task="balance", robot="armar4", executor="mjx", substeps=H.PHYSICS_SUBSTEPS)
    env = H.make_env(cfg, "test")
    fine = load_robot(H.STANDING_ROBOT)
    assert env.robot.mj_model.opt.timestep == pytest.approx(0.1 / H.PHYSICS_SUBSTEPS)
    assert env.robot.n_substeps == H.PHYSICS_SUBSTEPS  # (the env checks that executor and config take as many)
    n = env.robot.n_joints
    ratio = env.robot.mj_model.actuator_gainprm[:n, 0] / fine.mj_model.actuator_gainprm[:n, 0]  # kp ~ omega^2
    np.testing.assert_allclose(ratio, (H.PHYSICS_SUBSTEPS / 24) ** 2, rtol=1e-6)


def test_balance_weights_scale_only_the_balance_terms():
    none = H.balance_weights(0.0)
    assert (none.base_pos, none.base_orn, none.tilt, none.end_point) == (0, 0, 0, 0)
    assert dataclasses.replace(none, base_pos=0.2, base_orn=0.2, tilt=2.0, end_point=0.2) == H.BALANCE_WEIGHTS
    # the training config's weights (alpha etc. from its flags) get the papers' balance terms
    cfg = TrainConfig().replace(task="balance", robot="armar4", executor="mjx", alpha=2.0, action_reward=0.0)
    w = cfg.env_config().reward
    assert (w.distance, w.action, w.base_pos, w.base_orn, w.tilt, w.end_point) == (2.0, 0.0, 0.2, 0.2, 2.0, 0.2)
    half = cfg.replace(balance_reward=0.5).env_config().reward
    assert (half.base_pos, half.tilt) == (0.1, 1.0)
    assert cfg.replace(balance_reward=0.0).env_config().reward.tilt == 0.0
    assert TrainConfig().env_config().reward.tilt == 0.0  # plain path tracking: no balance terms


def test_leg_prior_holds_the_legs_of_the_controlled_legs_env_at_its_home(legs_robot):
    """``--leg-prior hold``: the prior built from the config alone (as evaluation and export
    rebuild it) holds exactly the environment's leg joints, at the environment's home, with its
    limits and decision step (that it reads the hold actions of the observed state:
    tests/envs/test_action_prior.py); it leaves the upper body's actions at 0."""
    env = make(legs_robot, "controlled")
    cfg = TrainConfig().replace(task="balance", robot="armar4", executor="mjx", legs="controlled", leg_prior="hold")
    prior = H.action_prior(cfg)
    legs = np.flatnonzero(~np.asarray(legs_robot.path_mask))
    assert len(legs) == 12 and prior.n == env.action_size == 30
    np.testing.assert_array_equal(prior.joints, legs)
    np.testing.assert_array_equal(np.asarray(prior.home), np.asarray(env.home)[legs])
    for field in ("pos_min", "pos_max", "vel", "acc", "jerk"):
        np.testing.assert_array_equal(np.asarray(getattr(prior.limits, field)),
                                      np.asarray(getattr(env.limits, field))[legs])
    assert prior.dt == pytest.approx(env.config.dt)
    obs = jnp.zeros((2, env.observation_size))
    assert np.all(np.asarray(prior(obs))[:, np.asarray(legs_robot.path_mask)] == 0.0)
    assert H.action_prior(cfg.replace(leg_prior="none")) is None
    with pytest.raises(ValueError, match="needs legs='controlled'"):
        H.action_prior(cfg.replace(legs="fixed"))
