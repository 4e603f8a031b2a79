"""Tests of mjx_pathtrack.robots.registry: registry, limits vs the tables of docs/limits.md and docs/robots.md, FK, tracking, ARMAR models.

MJX compilations are kept few (FK per robot, one batched tracking rollout); everything that does
not need MJX runs on MuJoCo C.
"""

from __future__ import annotations

import importlib.util

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.robots import registry as R
from mjx_pathtrack.robots.collision import in_collision
from mjx_pathtrack.robots.registry import load_robot
from mjx_pathtrack.robots.urdf_import import load_urdf
from robot_rollouts import safe_setpoints

TRACK_TOL = 1e-3  # rad


@pytest.fixture(scope="module")
def robots():
    cache = {}

    def get(name):
        if name not in cache:
            cache[name] = load_robot(name)
        return cache[name]

    return get


# --- registry and errors ---------------------------------------------------------------------

def test_unknown_robot_lists_known_names():
    with pytest.raises(ValueError, match="unknown robot 'ur5'.*iiwa, iiwa_ball, armar6, armar4, armar4_legs, armar4_standing"):
        load_robot("ur5")


def test_unknown_option_and_bad_time_step():
    with pytest.raises(ValueError, match="unknown option.*'gain'"):
        load_robot("iiwa", gain=3)
    with pytest.raises(ValueError, match="whole multiple"):
        load_robot("iiwa", dt=0.1, sim_dt=0.03)
    with pytest.raises(ValueError, match="sim_dt must be > 0"):
        load_robot("iiwa", sim_dt=0.0)


def test_servo_bandwidth_follows_the_physics_step_unless_given():
    """Default bandwidth 400 rad/s at 1/240 s, omega * sim_dt constant otherwise (kp = M omega^2,
    kv = 2 zeta M omega); an explicit ``servo_omega`` wins."""
    n = 7
    gains = lambda r: (r.mj_model.actuator_gainprm[:n, 0], r.mj_model.actuator_gainprm[n:2 * n, 0])  # noqa: E731
    kp240, kv240 = gains(load_robot("iiwa"))
    kp120, kv120 = gains(load_robot("iiwa", sim_dt=1 / 120))
    np.testing.assert_allclose(kp120, kp240 / 4, rtol=1e-6)
    np.testing.assert_allclose(kv120, kv240 / 2, rtol=1e-6)
    kp, kv = gains(load_robot("iiwa", sim_dt=1 / 120, servo_omega=400.0))
    np.testing.assert_allclose(kp, kp240, rtol=1e-6)
    np.testing.assert_allclose(kv, kv240, rtol=1e-6)


def test_missing_armar_names_the_extra(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "armar" else real(name, *a))
    with pytest.raises(ImportError, match=r'extra "humanoids".*pip install -e "\.\[humanoids\]"'):
        load_robot("armar6")


def test_wrong_joint_count_in_urdf(monkeypatch):
    monkeypatch.setitem(R.ROBOTS, "iiwa", R.dataclasses.replace(R.ROBOTS["iiwa"], n_joints=6))
    with pytest.raises(ValueError, match="has 7 movable joints, expected 6"):
        load_robot("iiwa")


def test_wrong_joint_count_in_arrays(robots):
    robot = robots("iiwa")
    for bad in (np.zeros(6), np.zeros((3, 8)), np.float32(0.0)):
        with pytest.raises(ValueError, match=r"shape \[\.\.\., 7\]"):
            robot.fk(bad)
        with pytest.raises(ValueError, match=r"shape \[\.\.\., 7\]"):
            in_collision(robot, bad)


@pytest.mark.parametrize("text,message", [
    ("<robot name='x'><link name='a'/>", "malformed URDF"),  # broken XML
    ("<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='revolute'><parent link='a'/>"
     "<child link='b'/><axis xyz='0 0 1'/></joint></robot>", "has no <limit>"),
    ("<robot name='x'><link name='a'/><joint name='j' type='fixed'><parent link='a'/><child link='c'/></joint>"
     "</robot>", "unknown link 'c'"),
    ("<robot name='x'><link name='a'/><link name='b'/></robot>", "expected one root link"),
    ("<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='fixed'><parent link='a'/>"
     "<child link='b'/><origin xyz='0 zero 0'/></joint></robot>", "malformed URDF"),
])
def test_malformed_urdf(tmp_path, text, message):
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_urdf(path)


def test_missing_urdf_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        load_urdf(tmp_path / "nope.urdf")


# --- joint counts and limits (docs/limits.md §3, docs/robots.md) --------------------------------------------

@pytest.mark.parametrize("name,n,n_path", [
    ("iiwa", 7, 7), ("iiwa_ball", 7, 7), ("armar6", 17, 17), ("armar4", 18, 18), ("armar4_legs", 30, 18),
    ("armar4_standing", 18, 18),
])
def test_joint_counts(robots, name, n, n_path):
    robot = robots(name)
    assert robot.n_joints == n == robot.limits.n_joints
    assert int(robot.path_mask.sum()) == n_path
    assert robot.mj_model.nu == 2 * n
    assert robot.n_substeps == 24


def test_iiwa_urdf_matches_reference_table():
    # docs/robots.md §1 table (the papers' URDF): lower/upper, velocity
    pos = [2.9670597283903604, 2.0943951023931953, 2.9670597283903604, 2.0943951023931953,
           2.9670597283903604, 2.0943951023931953, 3.0543261909900763]
    vel = [1.710422666954443, 1.710422666954443, 1.7453292519943295, 2.2689280275926285,
           2.443460952792061, 3.141592653589793, 3.141592653589793]
    urdf = load_urdf(R.IIWA_URDF)
    joints = [j for j in urdf.robot.joints if j.type == "revolute"]
    assert [j.name for j in joints] == list(iiwa.JOINT_NAMES)
    np.testing.assert_array_equal([j.limit.upper for j in joints], pos)
    np.testing.assert_array_equal([-j.limit.lower for j in joints], pos)
    np.testing.assert_array_equal([j.limit.velocity for j in joints], vel)
    assert sum(link.inertial.mass for link in urdf.robot.links if link.inertial) == pytest.approx(23.9)


def test_iiwa_limits_equal_iiwa_module(robots):
    expected = iiwa.joint_limits(0.1)
    for robot in (robots("iiwa"), robots("iiwa_ball")):
        assert robot.joint_names == iiwa.JOINT_NAMES
        for field in ("pos_min", "pos_max", "vel", "acc", "jerk"):
            np.testing.assert_array_equal(getattr(robot.limits, field), getattr(expected, field), err_msg=field)
    np.testing.assert_allclose(robots("iiwa").limits.jerk, [300, 150, 200, 250, 300, 400, 400], rtol=1e-6)
    # iiwa.py = the URDF limits minus the papers' 0.035 rad buffer, rounded to 5 digits
    urdf = [j for j in load_urdf(R.IIWA_URDF).robot.joints if j.type == "revolute"]
    np.testing.assert_allclose([j.limit.upper - R.POS_BUFFER for j in urdf], iiwa.POS, atol=1e-5)
    np.testing.assert_allclose([j.limit.velocity for j in urdf], iiwa.VEL, atol=1e-5)


def test_jerk_options():
    robot = load_robot("iiwa", dt=0.05, jerk_factor=0.5)
    np.testing.assert_allclose(robot.limits.jerk, 0.5 * 2 * iiwa.ACC / 0.05, rtol=1e-6)
    assert robot.n_substeps == 12


def _table(robot, table):
    """Compare ``{joint: (lo, hi, vel, acc)}`` (URDF limits of docs/robots.md §2-3) with robot.limits."""
    lim = robot.limits
    for joint, (lo, hi, vel, acc) in table.items():
        i = robot.joint_names.index(joint)
        # the table rounds to ~3-4 digits; our limits are the URDF values minus the 0.035 buffer
        assert float(lim.pos_min[i]) == pytest.approx(lo + R.POS_BUFFER, abs=2e-3), joint
        assert float(lim.pos_max[i]) == pytest.approx(hi - R.POS_BUFFER, abs=2e-3), joint
        assert float(lim.vel[i]) == pytest.approx(vel, abs=1e-5), joint
        assert float(lim.acc[i]) == acc, joint
        assert float(lim.jerk[i]) == pytest.approx(2 * acc / 0.1, rel=1e-6), joint


ARM6 = {"arm_t12_joint": (-1.3963, 1.3963), "arm_t23_joint": (-1.5708, 1.5708), "arm_t34_joint": (-0.24, 3.1),
        "arm_t45_joint": (-1.5708, 1.5708), "arm_t56_joint": (0.0, 2.51), "arm_t67_joint": (-1.5708, 1.5708),
        "arm_t78_joint": (-0.64, 0.64), "arm_t8_joint": (-1.52, 1.52)}
ARM4 = {"arm_sho1_joint": (0.0, 0.785, 0.6, 7.5), "arm_sho2_joint": (-0.524, 2.618, 1.71042, 15.0),
        "arm_sho3_joint": (-0.262, 1.396, 1.71042, 15.0), "arm_sho4_joint": (-1.396, 2.967, 1.71042, 15.0),
        "arm_elb1_joint": (-0.087, 1.815, 1.71042, 15.0), "arm_elb2_joint": (-3.1416, 1.5708, 1.71042, 15.0),
        "arm_wri1_joint": (-0.15, 0.15, 0.3, 15.0), "arm_wri2_joint": (-1.5708, 1.5708, 1.71042, 15.0)}
LEG4 = {"leg_hip1_joint": (-0.49, 1.58), "leg_hip2_joint": (-0.185, 0.654), "leg_hip3_joint": (-0.981, 0.818),
        "leg_knee_joint": (0.0, 1.635), "leg_ank1_joint": (-0.49, 0.49), "leg_ank2_joint": (-0.06, 0.06)}


def test_armar6_limits_match_reference(robots):
    table = {"torso_joint": (-0.365, 0.0, 0.15, 15.0)}
    for side in ("r0", "r1"):
        table.update({f"{j}_{side}": (lo, hi, 1.71042, 15.0) for j, (lo, hi) in ARM6.items()})
    robot = robots("armar6")
    assert len(table) == robot.n_joints == 17
    _table(robot, table)


@pytest.mark.parametrize("name", ["armar4", "armar4_legs", "armar4_standing"])
def test_armar4_limits_match_reference(robots, name):
    table = {"torso_yaw_joint": (-1.5708, 1.5708, 0.6, 7.0), "torso_pitch_joint": (-0.5, 0.5, 0.4, 4.5)}
    for side in ("r0", "r1"):
        table.update({f"{j}_{side}": v for j, v in ARM4.items()})
        if name == "armar4_legs":
            table.update({f"{j}_{side}": (lo, hi, 1.71042, 3.0) for j, (lo, hi) in LEG4.items()})
    robot = robots(name)
    assert len(table) == robot.n_joints
    _table(robot, table)
    np.testing.assert_array_equal(robot.path_mask, [not j.startswith("leg_") for j in robot.joint_names])


# --- forward kinematics ----------------------------------------------------------------------

def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_iiwa_fk_hand_computed(robots):
    """Shoulder at 0.34 m, elbow +0.40, wrist +0.40, TCP +0.126 (docs/robots.md §1); frames parallel at q = 0."""
    half = np.pi / 2
    q = np.zeros((3, 7))
    q[1, 1] = half  # joint 2 (axis y) by 90 deg: the arm above the shoulder points along +x
    q[2, 0], q[2, 3] = half, half  # joint 4 (axis -y) by 90 deg, then joint 1 (axis z) by 90 deg
    expected_pos = [[0, 0, 1.266], [0.926, 0, 0.34], [0, -0.526, 0.74]]
    expected_rot = [np.eye(3), _ry(half), _rz(half) @ _ry(-half)]
    pos, rot = jax.jit(robots("iiwa").fk)(jnp.asarray(q))
    assert pos.shape == (3, 1, 3) and rot.shape == (3, 1, 3, 3)
    np.testing.assert_allclose(pos[:, 0], expected_pos, atol=1e-6)
    np.testing.assert_allclose(rot[:, 0], expected_rot, atol=1e-6)


@pytest.mark.parametrize("name", ["iiwa", "armar6", "armar4_legs", "armar4_standing"])
def test_fk_agrees_with_mujoco(robots, name):
    robot = robots(name)
    rng = np.random.default_rng(1)
    lo, hi = np.asarray(robot.limits.pos_min), np.asarray(robot.limits.pos_max)
    q = rng.uniform(lo, hi, (2, 3, robot.n_joints))  # any batch shape
    pos, rot = jax.jit(robot.fk)(jnp.asarray(q, jnp.float32))
    assert pos.shape == (2, 3, len(robot.target_sites), 3)
    data = mujoco.MjData(robot.mj_model)
    for idx in np.ndindex(2, 3):
        data.qpos[:] = robot.qpos0
        data.qpos[robot.qpos_adr] = q[idx]
        mujoco.mj_kinematics(robot.mj_model, data)
        np.testing.assert_allclose(pos[idx], data.site_xpos[robot.site_ids], atol=2e-6)
        np.testing.assert_allclose(rot[idx], data.site_xmat[robot.site_ids].reshape(-1, 3, 3), atol=2e-6)
    # a change of q moves the target points (rules out FK ignoring q)
    assert float(jnp.abs(pos[0, 0] - pos[1, 2]).max()) > 1e-2


def test_armar_targets_are_two_hands(robots):
    for name in ("armar6", "armar4", "armar4_legs", "armar4_standing"):
        robot = robots(name)
        data = robot.mj_data()
        left, right = data.site_xpos[robot.site_ids]
        assert left[1] > 0.2 and right[1] < -0.2, name  # one hand on each side
        assert np.linalg.norm(left[[0, 2]] - right[[0, 2]]) < 0.05, name  # mirror-symmetric at q0


# --- self-collision --------------------------------------------------------------------------

def test_in_collision_iiwa(robots):
    robot = robots("iiwa")
    q = np.array([
        np.zeros(7),
        [0, 0, 0, 0, 0, 2.05, 0],  # wrist bent to its limit: the flange clears the forearm
        [0, 2.0, 0, -2.0, 0, 2.0, 0],  # arm folded down: flange hits the base
    ])
    np.testing.assert_array_equal(in_collision(robot, q), [False, False, True])
    assert in_collision(robot, q.reshape(3, 1, 7)).shape == (3, 1)
    rng = np.random.default_rng(0)
    random = in_collision(robot, rng.uniform(robot.limits.pos_min, robot.limits.pos_max, (500, 7)))
    assert random.mean() < 0.05  # the primitives are not bloated: random poses are mostly free


def test_in_collision_armar(robots):
    robot = robots("armar6")
    assert not in_collision(robot, robot.q0)
    rng = np.random.default_rng(2)
    samples = rng.uniform(robot.limits.pos_min, robot.limits.pos_max, (300, robot.n_joints))
    hits = in_collision(robot, samples)
    assert hits.any() and not hits.all()


# --- tracking of safe setpoint trajectories --------------------------------------------------

def test_mjx_tracking_iiwa(robots):
    """Random safe trajectories (limits.py) executed by MJX: positions within 1e-3 rad of the setpoints
    after every physics step."""
    robot = robots("iiwa")
    batch, steps = 8, 8
    q_start, v_mid, q_end = safe_setpoints(robot, jax.random.PRNGKey(0), steps, batch)
    assert np.ptp(q_end, axis=1).max() > 0.5  # the trajectories really move
    data = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), robot.mjx_data())
    ctrl = jnp.asarray(robot.ctrl(q_start, v_mid)).transpose(1, 0, 2)  # [time, batch, 2n]

    @jax.jit
    def rollout(data, ctrl):
        def body(d, c):
            d = jax.vmap(mjx.step, in_axes=(None, 0))(robot.mjx_model, d.replace(ctrl=c))
            return d, d.qpos[:, robot.qpos_adr]
        return jax.lax.scan(body, data, ctrl)[1]

    executed = np.asarray(rollout(data, ctrl)).transpose(1, 0, 2)
    err = np.abs(executed - q_end).max()
    assert err < TRACK_TOL, err


@pytest.mark.parametrize("name", ["armar6", "armar4"])
def test_tracking_armar_mujoco_c(robots, name):
    """Same check on the fixed-base humanoids with MuJoCo C (same model, no extra MJX compile)."""
    robot = robots(name)
    q_start, v_mid, q_end = safe_setpoints(robot, jax.random.PRNGKey(1), 6, 2)
    assert np.ptp(q_end, axis=1).max() > 0.3
    worst = 0.0
    for b in range(q_start.shape[0]):
        data = robot.mj_data()
        for i in range(q_start.shape[1]):
            data.ctrl[:] = np.concatenate([q_start[b, i], v_mid[b, i]])
            mujoco.mj_step(robot.mj_model, data)
            worst = max(worst, np.abs(data.qpos[robot.qpos_adr] - q_end[b, i]).max())
    assert worst < TRACK_TOL, worst


# --- ARMAR simulation ------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["armar6", "armar4", "armar4_legs", "armar4_standing"])
def test_armar_simulates(robots, name):
    robot = robots(name)
    data = robot.mj_data()
    for _ in range(10):
        mujoco.mj_step(robot.mj_model, data)
    assert np.all(np.isfinite(data.qpos)) and data.time == pytest.approx(10 * R.SIM_DT)
    assert robot.mjx_model.nq == robot.mj_model.nq  # the MJX model exists (benchmark runs it)


@pytest.mark.parametrize("name", ["armar4_legs", "armar4_standing"])
def test_armar4_floating_base_stands(robots, name):
    """Holding q0 for 1 s: the pelvis stays upright and in place, the joints hold their positions."""
    robot = robots(name)
    assert robot.floating
    model, data = robot.mj_model, robot.mj_data()
    base0 = data.qpos[:3].copy()
    for _ in range(240):
        mujoco.mj_step(model, data)
    up = np.zeros(9)
    mujoco.mju_quat2Mat(up, data.qpos[3:7])
    tilt = np.degrees(np.arccos(np.clip(up[8], -1, 1)))
    assert tilt < 1.0, tilt
    assert np.linalg.norm(data.qpos[:3] - base0) < 0.005
    assert np.abs(data.qpos[robot.qpos_adr] - robot.q0).max() < 2e-3
    assert data.ncon >= 4  # standing on its soles, not floating



def test_armar4_standing_is_armar4_legs_with_welded_legs(robots):
    """Same upper body, masses and pelvis, 12 fewer degrees of freedom; at any upper-body pose the
    target points and the pelvis site agree with ``armar4_legs`` at legs 0."""
    legs, standing = robots("armar4_legs"), robots("armar4_standing")
    upper = np.flatnonzero(legs.path_mask)
    assert standing.joint_names == tuple(legs.joint_names[i] for i in upper)
    assert standing.mj_model.nv == legs.mj_model.nv - 12 == 24
    assert standing.mj_model.body_subtreemass[0] == pytest.approx(legs.mj_model.body_subtreemass[0])
    np.testing.assert_allclose(standing.qpos0[:7], legs.qpos0[:7], atol=1e-9)  # same height above the floor
    q = np.random.default_rng(0).uniform(standing.limits.pos_min, standing.limits.pos_max)
    out = []
    for robot, qr in ((legs, np.zeros(legs.n_joints)), (standing, q)):
        qr[upper if robot is legs else slice(None)] = q
        data = mujoco.MjData(robot.mj_model)
        data.qpos[:] = robot.qpos0
        data.qpos[robot.qpos_adr] = qr
        mujoco.mj_kinematics(robot.mj_model, data)
        out.append((data.site_xpos[robot.site_ids], data.site_xpos[robot.mj_model.site("pelvis").id]))
    np.testing.assert_allclose(out[0][0], out[1][0], atol=1e-6)
    np.testing.assert_allclose(out[0][1], out[1][1], atol=1e-6)
    data = legs.mj_data()  # armar4_legs' pelvis site is its base body's centre of mass
    np.testing.assert_allclose(data.site_xpos[legs.mj_model.site("pelvis").id], data.xipos[1], atol=1e-9)
