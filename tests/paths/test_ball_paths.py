"""Ball-balancing dataset: level plate along the committed paths, limits, statistics, reflections,
determinism of the generator (through generate.py's kind registry)."""

from __future__ import annotations

import numpy as np
import pytest

from mjx_pathtrack.paths import datasets
from mjx_pathtrack.paths import generate
from mjx_pathtrack.paths import ball as G
from mjx_pathtrack.robots.registry import load_robot


@pytest.fixture(scope="module")
def kin():
    return G.PlateKinematics(load_robot("iiwa_ball"))


@pytest.fixture(scope="module")
def test_paths():
    return datasets.load_split("iiwa", "ball_balancing", "test")


def test_committed_paths_keep_the_plate_level_inside_the_limits(kin, test_paths):
    """FK of the fitted spline every 0.01 rad of arc length (not only the knots): tilt < 1 deg."""
    lim = load_robot("iiwa").limits
    worst = 0.0
    for knots in test_paths + datasets.load_split("iiwa", "ball_balancing", "train")[:20]:
        worst = max(worst, float(G.path_tilt_deg(kin, knots).max()))
        datasets.validate_path(knots, lim)
    assert worst < 1.0


def test_committed_statistics_match_the_papers_set(test_paths):
    """docs/paths.md §4 industrial/ball_balancing/test: knots 12/14/19, 3.2/3.8/5.1 rad, spacing 0.3."""
    st = datasets.split_stats(test_paths)
    assert st.n_paths == 200 and st.n_joints == 7
    assert 11 <= st.knots[0] and 13 <= st.knots[1] <= 16 and st.knots[2] <= 22
    assert 3.1 <= st.polyline_length[0] and 3.6 <= st.polyline_length[1] <= 4.1 and st.polyline_length[2] <= 5.5
    assert abs(st.spacing_median - 0.3) < 0.01
    config = datasets.read_config("iiwa", "ball_balancing")
    assert config["resampling_distance"] == 0.3 and config["curvature_sampling_distance"] is None
    assert np.asarray(config["reflection_vectors"]).shape == (4, 7)


def test_reflected_paths_stay_level(kin, test_paths):
    reflected = G.reflect_paths(test_paths[:3])
    assert len(reflected) == 12
    np.testing.assert_array_equal(reflected[1], -test_paths[0])
    assert max(float(G.path_tilt_deg(kin, p).max()) for p in reflected) < 1.0
    with pytest.raises(ValueError, match="reflection vectors have 7 joints"):
        G.reflect_paths([np.zeros((3, 6))])


def test_generation_is_deterministic_and_registered(tmp_path):
    dirs = [generate.generate_dataset("iiwa", "ball_balancing", 2, 1, seed=3, root=tmp_path / name)
            for name in ("a", "b")]
    for split in ("train", "test"):
        a, b = (datasets.load_split("iiwa", "ball_balancing", split, root=d.parents[1]) for d in dirs)
        assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    other = datasets.load_split("iiwa", "ball_balancing", "train", root=dirs[0].parents[1])
    assert not np.array_equal(other[0], other[1])
    with pytest.raises(datasets.DatasetError, match="iiwa only"):
        G.generate_ball_dataset("armar6", root=tmp_path / "c")


def test_a_user_ball_path_is_checked_for_a_level_plate(kin, test_paths):
    """A ball path from elsewhere is accepted when the plate stays level along it; a tilted one is
    refused naming the path, the knot nearest the tilt and the tilt."""
    level = test_paths[0]
    assert G.check_level(kin, level, name="mine") <= G.BallPathConfig.max_tilt_deg
    tilted = level.copy()
    tilted[5, 5] += 0.2    # the wrist pitch at knot 5: the plate tips by ~11 deg there
    with pytest.raises(datasets.DatasetError, match=r"^mine: the plate tilts 1\d\.\d\d deg near knot 5 "):
        G.check_level(kin, tilted, name="mine")


def test_whole_workspace_generator_covers_both_elbows_and_every_reach(kin):
    """``whole_workspace()``: level-plate paths with the elbow bent either way and the plate from
    near the base axis to full reach -- where the papers' generator never goes (elbow one way,
    plate 0.43-0.70 m out) -- each level along its spline and inside the limits; the papers'
    generator's committed paths stay reproducible with the defaults."""
    robot = load_robot("iiwa_ball")
    paths, counts = G.ball_paths(robot, 24, 5, G.whole_workspace())
    assert len(paths) == 24 and counts["attempts"] >= 24
    lim = load_robot("iiwa").limits
    for knots in paths:
        assert float(G.path_tilt_deg(kin, knots).max()) <= G.BallPathConfig.max_tilt_deg
        datasets.validate_path(knots, lim)
    elbow = np.array([p[0, 3] for p in paths])
    assert np.any(elbow > 0.2) and np.any(elbow < -0.2)
    radius = np.array([np.hypot(*kin.pose(q)[0][:2]) for p in paths for q in p])
    assert radius.min() < 0.3 and radius.max() > 0.6
    first, _ = G.ball_paths(robot, 2, 1)
    committed = datasets.load_split("iiwa", "ball_balancing", "test")
    assert all(np.array_equal(a, b) for a, b in zip(first, committed[:2]))


def test_the_command_line_generates_the_whole_workspace_set(tmp_path):
    """``generate --kind ball_balancing --param workspace=whole``: the same paths as
    ``generate_ball_dataset(cfg=whole_workspace())``, the settings recorded; unknown workspaces
    and parameters are named."""
    import subprocess
    import sys

    run = lambda *a: subprocess.run([sys.executable, "-m", "mjx_pathtrack.paths", "generate", "--kind",  # noqa: E731
                                     "ball_balancing", "--num-train", "0", "--num-test", "2", "--seed", "4", *a],
                                    capture_output=True, text=True)
    out = run("--root", str(tmp_path / "cli"), "--param", "workspace=whole")
    assert out.returncode == 0, out.stderr
    G.generate_ball_dataset("iiwa", 0, 2, 4, root=tmp_path / "py", cfg=G.whole_workspace())
    for x, y in zip(*(datasets.load_split("iiwa", "ball_balancing", "test", tmp_path / r) for r in ("cli", "py"))):
        np.testing.assert_array_equal(x, y)
    settings = datasets.read_config("iiwa", "ball_balancing", tmp_path / "cli")["source"]["settings"]
    assert settings["q2_range"] == list(G.whole_workspace().q2_range)
    out = run("--root", str(tmp_path / "bad"), "--param", "workspace=moon")
    assert out.returncode == 2 and "unknown ball workspace 'moon'" in out.stderr
    out = run("--root", str(tmp_path / "bad"), "--param", "elbow=1")
    assert out.returncode == 2 and "unknown generation parameter(s) ['elbow']" in out.stderr
    out = run("--root", str(tmp_path / "bad"), "--param", "workspace")
    assert out.returncode == 2 and "--param must be NAME=VALUE" in out.stderr
