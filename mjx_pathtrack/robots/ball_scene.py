"""Ball-on-plate scene: a plate fixed to the iiwa's flange and a free ball (docs/robots.md §1).

* Plate: box 0.3393 x 0.2715 x 0.002 m, centre 0.135 m along link 7's z, yaw -pi/2 (as the
  papers' board), mass 0.508 kg (the papers' board). Site ``plate`` at the centre of its top
  surface: x along the plate's long side, z the surface normal.
* Ball: free body ``ball`` with a sphere geom; default radius 28 mm and mass 0.1 kg; friction 1
  (the papers' lateral friction); ``condim = 3`` here, the ball task turns on rolling and
  spinning friction (``condim = 6``, :class:`~mjx_pathtrack.envs.tasks.ball_on_plate.BallExecutor`).
  Only ball-plate contacts exist (``contype``/``conaffinity`` bit 2).
* Physics option ``impratio`` = :data:`IMPRATIO` (1000), so that the ball's rolling friction acts,
  and :data:`ITERATIONS` Newton iterations (the registry's ``iiwa_ball`` entry), so that the solver converges.
* Sensor ``ball_in_plate`` (``framepos`` of site ``ball`` in site ``plate``): ball centre in the
  plate frame [m]; :func:`ball_in_plate_frame` computes the same from ``site_xpos``/``site_xmat``.
* :func:`sample_start_xy` draws the start position on the plate; :func:`ball_pose_on_plate`
  turns it into the ball's free-joint ``qpos``.
* :func:`randomize_ball` draws radius (20-36 mm) and mass (2-203 g) per episode as a new
  ``mjx.Model`` (pure JAX); :func:`randomize_balls` does it for a batch of keys and returns the
  ``in_axes`` tree for ``jax.vmap(mjx.step, in_axes=(axes, 0))``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

Array = jax.Array

PLATE_SIZE = (0.3393, 0.2715, 0.002)  # m (full extents)
PLATE_OFFSET = 0.135  # m along link 7's z
PLATE_MASS = 0.508  # kg
BALL_RADIUS = 0.028  # m, default (middle of the range)
BALL_MASS = 0.1  # kg, default (the papers' sphere.urdf)
RADIUS_RANGE = (0.020, 0.036)  # m
MASS_RANGE = (0.002, 0.203)  # kg
START_RANGE = (0.0797, 0.0458)  # m, half-ranges of the start position on the plate (x, y)
_CONTACT_BIT = 2
#: MuJoCo's ratio of frictional to normal constraint impedance for the ball's contact. MuJoCo's
#: contacts are soft: a frictional dimension's regulariser scales with 1/impratio and with
#: 1/mu^2, so at the default 1 the papers' rolling friction (1e-4..6e-4 m) barely acts: a ball on
#: a plate tilted by 0.1 deg rolls as if frictionless, where the papers' simulator (PyBullet, a
#: torque limit mu_r N) holds it still up to atan(mu_r / r) = 0.16..1.7 deg. 1000 (pyramidal
#: cone) makes it agree with PyBullet on whether the ball stays put in 77 % of a grid of tilts and
#: balls (27 % at 1); higher values or elliptic cones go unstable with the scene's implicit-fast
#: integrator and 4 iterations (docs/results.md "Ball on plate", ``tests/envs/test_ball_physics.py``)
IMPRATIO = 1000.0
#: Newton iterations of the ball scene's constraint solver. At :data:`IMPRATIO` the solver needs
#: more than the 4 that suffice elsewhere (``scene.SOLVER_ITERATIONS``): with 4 it stops short of
#: convergence during the fast motions a trained policy makes and the ball slips off the plate
#: (open-loop replay of a policy's plate motions in MuJoCo: 36.5 % falls at 4 iterations, 8 % at
#: 6, 7.5 % at 10 and 20, 3.5 % in the rolling-ball scene the motions came from)
ITERATIONS = 10


def add_plate_and_ball(spec: mujoco.MjSpec, link: str = "iiwa_link_7") -> None:
    """Add the plate (fixed to ``link``), the ball, the ``ball_in_plate`` sensor to an MjSpec."""
    parent = spec.body(link)
    if parent is None:
        raise ValueError(f"ball scene: link {link!r} not in the model")
    yaw = [np.cos(-np.pi / 4), 0.0, 0.0, np.sin(-np.pi / 4)]  # -pi/2 about z (w, x, y, z)
    plate = parent.add_body(name="plate", pos=[0.0, 0.0, PLATE_OFFSET], quat=yaw)
    _plate_geometry(plate, PLATE_MASS)
    _add_ball(spec)
    spec.option.impratio = IMPRATIO


def _plate_geometry(plate, mass: float) -> None:
    """The plate's box geom, site and (box) inertia of ``mass`` [kg] on body ``plate``."""
    half = np.asarray(PLATE_SIZE) / 2.0
    plate.explicitinertial = True
    plate.mass = mass
    plate.inertia = mass / 3.0 * np.array([half[1] ** 2 + half[2] ** 2, half[0] ** 2 + half[2] ** 2,
                                           half[0] ** 2 + half[1] ** 2])
    plate.add_geom(name="plate", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(half), contype=_CONTACT_BIT,
                   conaffinity=_CONTACT_BIT, condim=3, friction=[1.0, 0.005, 0.0001], rgba=[0.8, 0.8, 0.8, 1])
    plate.add_site(name="plate", pos=[0.0, 0.0, half[2]], size=[0.005, 0, 0])


def _add_ball(spec: mujoco.MjSpec) -> None:
    ball = spec.worldbody.add_body(name="ball")
    ball.add_freejoint(name="ball")
    ball.explicitinertial = True
    ball.mass = BALL_MASS
    ball.inertia = [0.4 * BALL_MASS * BALL_RADIUS**2] * 3
    ball.add_geom(name="ball", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[BALL_RADIUS, 0, 0], contype=_CONTACT_BIT,
                  conaffinity=_CONTACT_BIT, condim=3, friction=[1.0, 0.005, 0.0001], rgba=[0.9, 0.2, 0.1, 1])
    ball.add_site(name="ball", size=[0.005, 0, 0])
    spec.add_sensor(name="ball_in_plate", type=mujoco.mjtSensor.mjSENS_FRAMEPOS, objtype=mujoco.mjtObj.mjOBJ_SITE,
                    objname="ball", reftype=mujoco.mjtObj.mjOBJ_SITE, refname="plate")


#: mass [kg] of the plate of :func:`plate_and_ball_model`: so heavy that the ball's contact
#: forces cannot move it within a physics step (its motion is prescribed: overwritten every step)
PRESCRIBED_PLATE_MASS = 1e4


def plate_and_ball_model(full: mujoco.MjModel) -> mujoco.MjModel:
    """The plate and the ball of the ``iiwa_ball`` scene ``full`` without the arm: the plate on a
    free joint ``plate`` (``qpos[0:7]``, ``qvel[0:6]``; gravity compensated, mass
    :data:`PRESCRIBED_PLATE_MASS`) whose pose and velocity the caller prescribes before every
    step, the ball on its free joint after it, the ``ball_in_plate`` sensor, and ``full``'s
    physics options (time step, integrator, solver, iterations, disabled constraints)."""
    spec = mujoco.MjSpec()
    spec.modelname = "plate_and_ball"
    plate = spec.worldbody.add_body(name="plate")
    plate.add_freejoint(name="plate")
    plate.gravcomp = 1.0
    _plate_geometry(plate, PRESCRIBED_PLATE_MASS)
    _add_ball(spec)
    model = spec.compile()
    for name in ("timestep", "integrator", "solver", "cone", "iterations", "ls_iterations", "tolerance",
                 "ls_tolerance", "impratio", "disableflags", "enableflags", "gravity", "noslip_iterations"):
        setattr(model.opt, name, getattr(full.opt, name))
    return model


def ball_pose_on_plate(plate_pos: Array, plate_mat: Array, xy: Array, radius: Array) -> Array:
    """Free-joint ``qpos [..., 7]`` (position, unit quaternion) of a ball resting on the plate at
    ``xy [..., 2]`` [m] in the plate frame; ``plate_pos [..., 3]``/``plate_mat [..., 3, 3]``: site
    ``plate`` pose (``site_xpos``, ``site_xmat``); ``radius [...]`` [m]. Pure JAX."""
    xp = jnp if isinstance(plate_pos, jax.Array) else np
    local = xp.concatenate([xy, radius[..., None]], axis=-1)
    pos = plate_pos + xp.einsum("...ij,...j->...i", plate_mat.reshape(plate_mat.shape[:-2] + (3, 3)), local)
    quat = xp.broadcast_to(xp.asarray([1.0, 0.0, 0.0, 0.0]), pos.shape[:-1] + (4,))
    return xp.concatenate([pos, quat], axis=-1)


def sample_start_xy(key: Array, shape: tuple[int, ...] = ()) -> Array:
    """Random ball start position on the plate ``[*shape, 2]`` [m], uniform in
    ``±START_RANGE`` (the papers' ±0.0797 x ±0.0458 m). Pure JAX."""
    return jax.random.uniform(key, shape + (2,), minval=-jnp.asarray(START_RANGE), maxval=jnp.asarray(START_RANGE))


def ball_on_plate_qpos(model: mujoco.MjModel, qpos: np.ndarray, xy=(0.0, 0.0)) -> np.ndarray:
    """``qpos`` with the ball resting on the plate at ``xy`` [m] (plate frame), robot pose from ``qpos``."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    site = model.site("plate").id
    radius = model.geom_size[model.geom("ball").id, 0]
    out = np.array(qpos, dtype=np.float64)
    adr = model.jnt_qposadr[model.joint("ball").id]
    out[adr:adr + 7] = ball_pose_on_plate(data.site_xpos[site], data.site_xmat[site].reshape(3, 3),
                                          np.asarray(xy, dtype=np.float64), np.asarray(radius))
    return out


def ball_in_plate_frame(site_xpos: Array, site_xmat: Array, plate_site: int, ball_site: int) -> Array:
    """Ball centre in the plate frame [m], ``[..., 3]``, from (batched) ``site_xpos [..., nsite, 3]``
    and ``site_xmat [..., nsite, 3, 3]`` (``mjx.Data`` fields). Pure JAX."""
    mat = site_xmat[..., plate_site, :, :]
    return jnp.einsum("...ji,...j->...i", mat, site_xpos[..., ball_site, :] - site_xpos[..., plate_site, :])


#: mjx.Model fields that :func:`randomize_ball` changes
RANDOMIZED_FIELDS = ("geom_size", "geom_rbound", "body_mass", "body_inertia", "body_invweight0", "dof_invweight0")


def ball_ids(model: mujoco.MjModel) -> tuple[int, int, int]:
    """``(body id, geom id, first dof address)`` of the ball."""
    return model.body("ball").id, model.geom("ball").id, int(model.jnt_dofadr[model.joint("ball").id])


def randomized_axes(mjx_model):
    """``in_axes`` tree for a model batch from :func:`randomize_balls`: 0 on ``RANDOMIZED_FIELDS``."""
    return jax.tree.map(lambda _: None, mjx_model).tree_replace({f: 0 for f in RANDOMIZED_FIELDS})


def randomize_balls(mjx_model, keys: Array, ids: tuple[int, int, int]):
    """Batch version of :func:`randomize_ball` over ``keys [B, 2]``: returns ``(models, axes,
    radius [B], mass [B])`` where only ``RANDOMIZED_FIELDS`` carry the batch axis (``axes``)."""
    axes = randomized_axes(mjx_model)
    models, radius, mass = jax.vmap(lambda k: randomize_ball(mjx_model, k, *ids), out_axes=(axes, 0, 0))(keys)
    return models, axes, radius, mass


def sample_ball(key: Array) -> tuple[Array, Array]:
    """The ball's radius ~ U(20, 36) mm and mass ~ U(2, 203) g drawn from ``key``: ``(radius [m],
    mass [kg])``, scalars. Pure JAX."""
    k_r, k_m = jax.random.split(key)
    radius = jax.random.uniform(k_r, (), minval=RADIUS_RANGE[0], maxval=RADIUS_RANGE[1])
    mass = jax.random.uniform(k_m, (), minval=MASS_RANGE[0], maxval=MASS_RANGE[1])
    return radius, mass


def randomize_ball(mjx_model, key: Array, ball_body: int, ball_geom: int, ball_dof: int):
    """A copy of ``mjx_model`` with the ball's radius ~ U(20, 36) mm and mass ~ U(2, 203) g
    (solid-sphere inertia). Also updates the fields derived from them at compile time
    (``geom_rbound``, ``body_invweight0``, ``dof_invweight0``). Pure JAX; ``jax.vmap`` over keys
    gives a batch of models (use ``in_axes`` for the changed fields). Returns ``(model, radius, mass)``.
    """
    radius, mass = sample_ball(key)
    inertia = 0.4 * mass * radius**2
    model = mjx_model.tree_replace({
        "geom_size": mjx_model.geom_size.at[ball_geom, 0].set(radius),
        "geom_rbound": mjx_model.geom_rbound.at[ball_geom].set(radius),
        "body_mass": mjx_model.body_mass.at[ball_body].set(mass),
        "body_inertia": mjx_model.body_inertia.at[ball_body].set(jnp.full(3, inertia)),
        "body_invweight0": mjx_model.body_invweight0.at[ball_body].set(jnp.stack([1.0 / mass, 1.0 / inertia])),
        "dof_invweight0": mjx_model.dof_invweight0.at[ball_dof:ball_dof + 6].set(
            jnp.concatenate([jnp.full(3, 1.0 / mass), jnp.full(3, 1.0 / inertia)])),
    })
    return model, radius, mass
