"""Path families of the generalisation benchmark (paths/families.py): what each promises."""
import numpy as np
import pytest

from mjx_pathtrack.core.spline_fit import fit_spline
from mjx_pathtrack.paths import families as F
from mjx_pathtrack.paths import ik
from mjx_pathtrack.robots.collision import in_collision
from mjx_pathtrack.robots.registry import POS_BUFFER, load_robot


@pytest.fixture(scope="module")
def robot():
    return load_robot("iiwa")


def _inside(robot, knots, allowance=0.0):
    lo = np.asarray(robot.limits.pos_min) - allowance - 1e-9
    hi = np.asarray(robot.limits.pos_max) + allowance + 1e-9
    return bool(np.all(knots >= lo) & np.all(knots <= hi))


@pytest.mark.parametrize("family", sorted(F.FAMILIES))
def test_family_is_deterministic_valid_and_collision_free(robot, family):
    paths = F.FAMILIES[family](robot, 2, 3)
    again = F.FAMILIES[family](robot, 2, 3)
    assert len(paths) == 2
    for p, q in zip(paths, again):
        np.testing.assert_array_equal(p, q)
        assert p.ndim == 2 and p.shape[1] == 7 and np.all(np.isfinite(p))
        assert _inside(robot, p, POS_BUFFER if family == "near_limits" else 0.0)
        fit = fit_spline(p)
        samples = fit.point_at(np.linspace(0.0, fit.length, 200))
        assert not in_collision(robot, np.clip(samples, robot.limits.pos_min, robot.limits.pos_max)).any()


def test_cartesian_line_family_follows_straight_segments(robot):
    """The tool points of a seam path lie on a few straight lines: consecutive 5 mm steps keep
    their direction except at the corners."""
    q = F.cartesian_lines(robot, 1, 0)[0]
    x = ik.target_positions(robot, q)[:, 0]
    step = np.diff(x, axis=0)
    length = np.linalg.norm(step, axis=-1)
    assert np.median(length) == pytest.approx(F.CARTESIAN_STEP, rel=0.05)   # IK tolerance 1 mm
    d = step / length[:, None]
    turns = np.sum(np.einsum("ij,ij->i", d[1:], d[:-1]) < 0.9)
    assert turns <= 4, f"{turns} direction changes, a seam has at most 3 corners"


def test_cartesian_circle_family_keeps_its_radius(robot):
    q = F.cartesian_circles(robot, 1, 1)[0]
    x = ik.target_positions(robot, q)[:, 0]
    centre = x.mean(0) if np.linalg.norm(x[0] - x[-1]) < 1e-2 else None
    # a circle (or arc) in a plane: the points' distances from their best-fit plane are ~0
    c = x - x.mean(0)
    normal = np.linalg.svd(c)[2][-1]
    assert np.max(np.abs(c @ normal)) < 2e-3
    if centre is not None:
        r = np.linalg.norm(x - centre, axis=-1)
        assert r.max() - r.min() < 4e-3


def test_near_limit_family_touches_the_urdf_limits(robot):
    p = F.near_limits(robot, 1, 0)[0]
    hi = np.asarray(robot.limits.pos_max)
    assert np.max(np.abs(p) - hi) == pytest.approx(POS_BUFFER, abs=1e-9)


def test_cartesian_families_refuse_robots_with_two_hands():
    class TwoHands:
        name, target_sites, path_mask = "two", ("a", "b"), np.ones(3, bool)

    with pytest.raises(ValueError, match="one target site"):
        F.cartesian_lines(TwoHands(), 1, 0)


def test_level_plate_family_carries_the_plate_level_and_horizontally(robot):
    """Ball paths from outside the training generator: deterministic, level along the whole
    spline (0.5 deg), the plate centre moving in a horizontal plane, inside the limits; elbows
    of both signs over a handful of paths; refused for another robot."""
    from mjx_pathtrack.paths import ball

    paths = F.level_plate(robot, 6, 2)
    again = F.level_plate(robot, 6, 2)
    kin = ball.PlateKinematics(load_robot("iiwa_ball"))
    for p, q in zip(paths, again):
        np.testing.assert_array_equal(p, q)
        assert _inside(robot, p)
        assert float(ball.path_tilt_deg(kin, p).max()) <= ball.BallPathConfig.max_tilt_deg
        heights = np.array([kin.pose(x)[0][2] for x in p])
        assert np.ptp(heights) < 0.005   # a horizontal tray path (IK tolerance 1 mm)
    elbows = np.array([p[0, 3] for p in F.level_plate(robot, 16, 9)])
    assert np.any(elbows > 0) and np.any(elbows < 0)
    with pytest.raises(ValueError, match="iiwa only"):
        F.level_plate(load_robot("armar6"), 1, 0)


def test_papers_ball_region_family_reflects_the_training_generator_and_stays_level(robot):
    """The papers' ball region: the training generator's paths (papers' start poses), path ``i``
    multiplied by reflection vector ``i % 4``, each level along its spline and inside the limits."""
    from mjx_pathtrack.paths import ball

    paths = F.papers_ball_region(robot, 4, 3)
    plain, _ = ball.ball_paths(load_robot("iiwa_ball", dt=0.1), 4, 3)
    kin = ball.PlateKinematics(load_robot("iiwa_ball"))
    for i, (p, q) in enumerate(zip(paths, plain)):
        np.testing.assert_array_equal(p, q * np.asarray(ball.REFLECTION_VECTORS[i]))
        assert _inside(robot, p)
        assert float(ball.path_tilt_deg(kin, p).max()) <= ball.BallPathConfig.max_tilt_deg
    with pytest.raises(ValueError, match="iiwa only"):
        F.papers_ball_region(load_robot("armar6"), 1, 0)
