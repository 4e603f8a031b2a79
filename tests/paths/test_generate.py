"""Dataset generation: deterministic, inside the limits, collision-free, rejecting collisions."""

import json

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401

from mjx_pathtrack.paths import datasets
from mjx_pathtrack.paths import generate
from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.robots import registry as robots
from mjx_pathtrack.robots.collision import in_collision


def test_random_paths_deterministic_and_inside_limits():
    lim = iiwa.joint_limits(0.1)
    a = generate.random_paths(lim, 3, seed=7, steps=12)
    b = generate.random_paths(lim, 3, seed=7, steps=12)
    c = generate.random_paths(lim, 3, seed=8, steps=12)
    assert len(a) == 3
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a[0][:5], c[0][:5])
    for knots in a:
        assert knots.shape[1] == 7 and len(knots) >= 2
        assert np.all(knots <= np.asarray(lim.pos_max) + 1e-6) and np.all(knots >= np.asarray(lim.pos_min) - 1e-6)
        # consecutive knots are spread by curvature resampling, none repeated
        assert np.all(np.linalg.norm(np.diff(knots, axis=0), axis=1) > 0)


def test_colliding_motions_are_rejected():
    lim = iiwa.joint_limits(0.1)
    seen = []

    def fake_collision(q):  # flags every motion whose start has joint 1 above 0
        seen.append(q.shape)
        hit = np.zeros(q.shape[:-1], bool)
        hit[:, 0] = q[:, 0, 0] > 0.0
        return hit

    paths = generate.random_paths(lim, 4, seed=3, steps=6, in_collision=fake_collision)
    assert len(paths) == 4
    assert all(p[0, 0] <= 0.0 for p in paths)
    assert seen and seen[0][0] == 4  # checked per batch of motions, every setpoint


def test_generate_dataset_writes_a_loadable_collision_free_dataset(tmp_path):
    directory = generate.generate_dataset("iiwa", "random", num_train=2, num_test=2, seed=1, root=tmp_path, steps=10)
    config = json.loads((directory / "config.json").read_text())
    assert config["num_train"] == 2 and config["n_joints"] == 7 and config["max_dis_between_knots"] > 0
    robot = robots.load_robot("iiwa")
    for split in ("train", "test"):
        knots = datasets.load_split("iiwa", "random", split, root=tmp_path)
        assert len(knots) == 2
        assert not np.any(in_collision(robot, np.concatenate(knots)))
    with pytest.raises(datasets.DatasetError, match="exists"):
        generate.generate_dataset("iiwa", "random", 1, 1, root=tmp_path)
    with pytest.raises(datasets.DatasetError, match="unknown robot"):
        generate.generate_dataset("ur5", "random", 1, 1, root=tmp_path)
