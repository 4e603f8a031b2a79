"""Ball-on-plate scene in MJX: sphere-box contact, plate-frame sensor, per-episode randomisation.

One jitted MJX rollout (2 s, two environments with randomised balls: plate level / tilted 30 deg)
covers the physics tests.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from mjx_pathtrack.robots import ball_scene as B
from mjx_pathtrack.robots.registry import load_robot

TILT = np.radians(30.0)


@pytest.fixture(scope="module")
def robot():
    return load_robot("iiwa_ball")


def test_scene_layout(robot):
    model, data = robot.mj_model, robot.mj_data()
    plate = model.geom("plate").id
    np.testing.assert_allclose(2 * model.geom_size[plate], B.PLATE_SIZE)
    # plate centre 0.135 m beyond the link 7 frame (joints 6/7), along its z axis, at q = 0
    link7 = model.body("iiwa_link_7").id
    np.testing.assert_allclose(data.geom_xpos[plate] - data.xpos[link7], [0, 0, 0.135], atol=1e-9)
    # the ball starts resting on the plate centre; the sensor reads its centre in the plate frame
    sensor = model.sensor("ball_in_plate")
    np.testing.assert_allclose(data.sensordata[sensor.adr[0]:sensor.adr[0] + 3], [0, 0, B.BALL_RADIUS], atol=1e-9)
    # only ball-plate contacts exist
    colliding = [g for g in range(model.ngeom) if model.geom_contype[g] or model.geom_conaffinity[g]]
    assert sorted(model.geom(g).name for g in colliding) == ["ball", "plate"]


def test_randomize_ball_ranges(robot):
    model = robot.mj_model
    ids = B.ball_ids(model)
    keys = jax.random.split(jax.random.PRNGKey(0), 256)
    models, _, radius, mass = B.randomize_balls(robot.mjx_model, keys, ids)
    assert 0.020 <= float(radius.min()) < 0.022 and 0.034 < float(radius.max()) <= 0.036
    assert 0.002 <= float(mass.min()) < 0.01 and 0.19 < float(mass.max()) <= 0.203
    np.testing.assert_allclose(models.geom_size[:, ids[1], 0], radius)
    np.testing.assert_allclose(models.body_mass[:, ids[0]], mass)
    np.testing.assert_allclose(models.body_inertia[:, ids[0], 0], 0.4 * mass * radius**2, rtol=1e-6)
    # the other fields stay shared (unbatched) and unchanged
    assert models.geom_pos.shape == robot.mjx_model.geom_pos.shape
    others = np.arange(model.ngeom) != ids[1]
    assert np.all(np.asarray(models.geom_size)[:, others] == np.asarray(robot.mjx_model.geom_size)[others])

def test_ball_on_level_and_tilted_plate_mjx(robot):
    """2 s of MJX physics with a random ball: stays put on a level, still plate; rolls off at 30 deg."""
    model = robot.mj_model
    ids = B.ball_ids(model)
    plate_site, ball_site = model.site("plate").id, model.site("ball").id
    sensor = model.sensor("ball_in_plate").adr[0]
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    models, axes, radius, _ = B.randomize_balls(robot.mjx_model, keys, ids)

    q = np.zeros((2, 7))
    q[1, 5] = TILT  # joint 6 (axis y) tilts the plate by 30 deg about its short side
    qpos = np.stack([robot.qpos0] * 2)
    qpos[:, robot.qpos_adr] = q
    data0 = robot.mjx_data()

    def reset(m, qpos_i, q_i, r):
        d = mjx.kinematics(m, data0.replace(qpos=qpos_i))
        ball = B.ball_pose_on_plate(d.site_xpos[plate_site], d.site_xmat[plate_site], jnp.zeros(2), r)
        adr = model.jnt_qposadr[model.joint("ball").id]
        return data0.replace(qpos=qpos_i.at[adr:adr + 7].set(ball), ctrl=robot.ctrl(q_i, jnp.zeros(7)))

    @jax.jit
    def run(models, qpos, q, radius):
        data = jax.vmap(reset, in_axes=(axes, 0, 0, 0))(models, jnp.asarray(qpos, jnp.float32), jnp.asarray(q), radius)
        step = jax.vmap(mjx.step, in_axes=(axes, 0))

        def body(d, _):
            d = step(models, d)
            return d, d.sensordata[:, sensor:sensor + 3]

        final, trace = jax.lax.scan(body, data, None, length=480)
        return final, trace

    final, trace = run(models, qpos, q, radius)
    trace = np.asarray(trace)  # [480, 2, 3] ball centre in the plate frame
    radius = np.asarray(radius)
    # the sensor agrees with the pure-JAX helper
    np.testing.assert_allclose(trace[-1], B.ball_in_plate_frame(final.site_xpos, final.site_xmat, plate_site, ball_site),
                               atol=1e-6)
    level = trace[:, 0]
    assert np.abs(level[:, :2]).max() < 1e-3, np.abs(level[:, :2]).max()  # stays at the centre
    assert np.abs(level[:, 2] - radius[0]).max() < 2e-3  # resting on the surface (soft contact)
    tilted = trace[:, 1]
    half = np.asarray(B.PLATE_SIZE[:2]) / 2
    assert np.abs(tilted[:, 2] - radius[1])[:10].max() < 2e-3  # starts on the surface
    off = np.flatnonzero((np.abs(tilted[:, :2]) > half).any(axis=1))
    assert off.size and off[0] * robot.mj_model.opt.timestep < 1.0, "ball did not roll off within 1 s"
    assert tilted[-1, 2] < -0.1  # and fell below the plate
    # it rolled down the slope: along the plate's y axis (joint 6 tilts about the plate's x axis)
    assert np.abs(tilted[off[0], 1]) > half[1] and np.abs(tilted[off[0], 0]) < 0.01


def test_sample_start_xy():
    xy = np.asarray(B.sample_start_xy(jax.random.PRNGKey(0), (4000,)))
    assert xy.shape == (4000, 2)
    np.testing.assert_allclose(np.abs(xy).max(axis=0), B.START_RANGE, rtol=2e-3)
    assert np.all(np.abs(xy) <= np.asarray(B.START_RANGE))


def test_ball_pose_on_plate_numpy_and_jax_agree():
    pos, mat = np.array([0.1, 0.2, 1.0]), np.eye(3)[[1, 0, 2]] * np.array([1, -1, 1])[:, None]
    a = B.ball_pose_on_plate(pos, mat, np.array([0.01, 0.02]), np.asarray(0.03))
    b = B.ball_pose_on_plate(jnp.asarray(pos), jnp.asarray(mat), jnp.array([0.01, 0.02]), jnp.asarray(0.03))
    np.testing.assert_allclose(a, b, atol=1e-6)
    np.testing.assert_allclose(a[:3], pos + mat @ [0.01, 0.02, 0.03])
    np.testing.assert_array_equal(a[3:], [1, 0, 0, 0])
