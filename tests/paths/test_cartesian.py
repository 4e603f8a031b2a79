"""Cartesian tool paths made joint paths (mjx_pathtrack.paths.cartesian): lines and circles of the
iiwa's TCP with known geometry, the IK residual along them, continuity, and bad input named by
waypoint; the import command and OnlineTracker.set_cartesian_path."""
from pathlib import Path

import numpy as np
import pytest

import mjx_pathtrack

mjx_pathtrack.prepare_xla()

from mjx_pathtrack.paths import cartesian as C  # noqa: E402
from mjx_pathtrack.paths import ik  # noqa: E402
from mjx_pathtrack.paths.datasets import DatasetError  # noqa: E402
from mjx_pathtrack.robots import registry as robots  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
#: a configuration in the middle of the iiwa's workspace (elbow bent, tool in front of the base)
Q_A = np.array([0.3, 0.7, 0.0, -1.3, 0.0, 0.9, 0.0])


@pytest.fixture(scope="module")
def robot():
    return robots.load_robot("iiwa")


def _tool(robot, q):
    return ik.target_positions(robot, np.atleast_2d(q))[:, 0]


def _line(robot):
    x0 = _tool(robot, Q_A)[0]
    return np.stack([x0, x0 + [0.10, 0.05, -0.04], x0 + [0.15, 0.12, 0.0]])


def _circle(robot, radius=0.08, count=25):
    x0 = _tool(robot, Q_A)[0]
    centre = x0 - [0.0, radius, 0.0]          # the circle starts at the tool, in a plane tilted about x
    a = np.linspace(0.0, 2 * np.pi, count)
    u, v = np.array([0.0, 1.0, 0.0]), np.array([np.sqrt(0.5), 0.0, np.sqrt(0.5)])
    return centre + radius * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v), centre, radius, np.cross(u, v)


def test_a_line_becomes_a_continuous_joint_path_on_the_line(robot):
    points = _line(robot)
    out = C.tool_path_to_joints(robot, points, Q_A, "seam")
    dense, rows = C.densify(points)
    np.testing.assert_array_equal(out.waypoint_rows, rows)
    assert len(out.joints) == len(dense) and np.all(np.diff(rows) >= 1)
    assert np.max(np.linalg.norm(np.diff(dense, axis=0), axis=-1)) <= C.SOLVE_SPACING + 1e-12
    reached = _tool(robot, out.joints)
    error = np.linalg.norm(reached - dense, axis=-1)
    assert error.max() <= C.MAX_RESIDUAL
    np.testing.assert_allclose(out.residual, error, atol=2e-5)     # the reported residual is the FK error
    assert np.max(np.abs(np.diff(out.joints, axis=0))) <= C.MAX_JOINT_JUMP
    lo, hi = np.asarray(robot.limits.pos_min), np.asarray(robot.limits.pos_max)
    assert np.all(out.joints >= lo) and np.all(out.joints <= hi)
    assert np.max(np.abs(out.joints[0] - Q_A)) < 0.05               # continues from the start configuration
    assert "residual max" in out.report_line()


def test_a_circle_stays_on_its_circle_and_closes(robot):
    points, centre, radius, normal = _circle(robot)
    out = C.tool_path_to_joints(robot, points, Q_A, "circle")
    reached = _tool(robot, out.joints)
    rel = reached - centre
    assert np.max(np.abs(np.linalg.norm(rel, axis=-1) - radius)) <= 1.5e-3   # on the circle (chords: 5 mm)
    assert np.max(np.abs(rel @ normal)) <= C.MAX_RESIDUAL                    # in its plane
    assert np.linalg.norm(reached[-1] - reached[0]) <= 2 * C.MAX_RESIDUAL    # closed
    assert np.max(np.abs(np.diff(out.joints, axis=0))) <= C.MAX_JOINT_JUMP


def test_without_a_start_configuration_the_first_waypoint_is_solved(robot):
    out = C.tool_path_to_joints(robot, _line(robot), None, "seam")
    assert out.residual.max() <= C.MAX_RESIDUAL
    np.testing.assert_allclose(_tool(robot, out.joints[-1])[0], _line(robot)[-1], atol=C.MAX_RESIDUAL)


def test_bad_tool_paths_are_named_by_waypoint(robot):
    line = _line(robot)
    with pytest.raises(DatasetError, match=r"seam: waypoint 1 is not finite"):
        C.tool_path_to_joints(robot, np.where(np.arange(3)[:, None] == 1, np.nan, line), Q_A, "seam")
    far = np.concatenate([line, line[-1:] + [0.0, 0.0, 2.5]])
    with pytest.raises(DatasetError, match=r"seam: waypoint 2 .* cannot be followed: the tool misses"):
        C.tool_path_to_joints(robot, far, Q_A, "seam")
    with pytest.raises(DatasetError, match="orientations are not supported"):
        C.tool_path_to_joints(robot, np.zeros((3, 7)), Q_A, "seam")
    with pytest.raises(DatasetError, match="at least 2 waypoints"):
        C.tool_path_to_joints(robot, line[:1], Q_A, "seam")
    with pytest.raises(DatasetError, match="start configuration must be 7 finite"):
        C.tool_path_to_joints(robot, line, np.zeros(6), "seam")


def test_import_cartesian_writes_a_joint_dataset(tmp_path, capsys):
    from mjx_pathtrack.paths import cli
    from mjx_pathtrack.paths.datasets import load_split, read_config

    robot = robots.load_robot("iiwa")
    points = _line(robot)
    file = tmp_path / "seam.csv"
    file.write_text("x,y,z\n" + "\n".join(",".join(f"{v:.6f}" for v in p) for p in points) + "\n")
    start = ",".join(str(v) for v in Q_A)
    args = ["import", str(file), "--robot", "iiwa", "--kind", "seam", "--root", str(tmp_path / "s"), "--cartesian"]
    assert cli.main(args + ["--start", start]) == 0
    out = capsys.readouterr().out
    assert "IK points, residual max" in out and "imported into" in out
    source = read_config("iiwa", "seam", tmp_path / "s")["source"]["test"]
    assert source["cartesian"]["ik_residual_mm_max"] <= 1000 * C.MAX_RESIDUAL
    (knots,) = load_split("iiwa", "seam", "test", tmp_path / "s")
    end = _tool(robot, knots[-1])[0]
    np.testing.assert_allclose(end, points[-1], atol=2e-3)   # re-knotted: the end knot is the path's end
    assert cli.main(["import", str(file), "--robot", "iiwa", "--kind", "x", "--root", str(tmp_path / "s"),
                     "--start", start]) == 2
    assert "--start applies to --cartesian only" in capsys.readouterr().err
    assert not (tmp_path / "s" / "iiwa" / "x").exists()


def test_online_tracker_follows_a_cartesian_line():
    """The shipped iiwa policy given a tool line through the tracker: it tracks the joint path of
    the line to its end and stops there as the policy stops (every joint within the stop's
    end-knot tolerance, 0.05 rad, of the IK solution of the last waypoint: the tool a few cm from
    the line's end)."""
    from mjx_pathtrack.deploy.controller import OnlineTracker, PathError, Status
    from mjx_pathtrack.deploy.export import load_policy

    robot = robots.load_robot("iiwa")
    tracker = OnlineTracker(load_policy(REPO / "policies" / "iiwa" / "export"), Q_A, controller_dt=0.01)
    with pytest.raises(PathError, match="waypoint 1 is not finite"):
        tracker.set_cartesian_path(np.array([[0.5, 0.0, 0.5], [np.nan, 0.0, 0.5]]))
    line = _line(robot)
    tracker.set_cartesian_path(line)
    assert tracker.status is not Status.STOPPED
    reached = False
    for _ in range(200):
        out = tracker.step()
        reached |= out.reached_end
        if out.status is Status.STOPPED:
            break
    assert tracker.status is Status.STOPPED and reached and tracker.fault is None
    end = C.tool_path_to_joints(robot, line, Q_A).joints[-1]
    assert np.max(np.abs(tracker.position - end)) <= 0.05 + 1e-3
    assert np.linalg.norm(_tool(robot, tracker.position)[0] - line[-1]) < 0.05
