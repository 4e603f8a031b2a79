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


def _turning(knots: np.ndarray) -> np.ndarray:
    """Turning angle per arc length [rad/rad] of the spline through ``knots``, every 0.01 rad."""
    from mjx_pathtrack.core.spline_fit import fit_spline

    fit = fit_spline(knots)
    d = np.diff(fit.point_at(np.linspace(0.0, fit.length, int(fit.length / 0.01) + 1)), axis=0)
    t = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.arccos(np.clip(np.sum(t[1:] * t[:-1], axis=1), -1.0, 1.0)) / 0.01


def test_persistent_agent_holds_its_actions_and_draws_smoother_curves():
    """``hold``: every setpoint inside the position and velocity limits; joints cruise near
    their velocity limit far more often than with a new action every step, and the curves bend
    less (the point of the persistent_random kind); a hold below one step is refused."""
    import jax

    lim = iiwa.joint_limits(0.1)
    q = np.asarray(generate.random_motions(lim, jax.random.PRNGKey(0), 16, 60, 0.1, 24, hold=(2, 8)))
    q_step = np.asarray(generate.random_motions(lim, jax.random.PRNGKey(0), 16, 60, 0.1, 24))
    dt = 0.1 / 24
    for motion in (q, q_step):
        v = np.diff(motion, axis=1) / dt
        assert np.all(motion <= np.asarray(lim.pos_max) + 1e-6) and np.all(motion >= np.asarray(lim.pos_min) - 1e-6)
        assert np.all(np.abs(v) <= np.asarray(lim.vel) * (1 + 1e-3))
    # near a velocity limit: the persistent agent cruises there far more often
    speed = lambda m: np.abs(np.diff(m[:, ::24], axis=1) / 0.1) / np.asarray(lim.vel)  # noqa: E731
    assert np.mean(speed(q) > 0.9) > 2 * np.mean(speed(q_step) > 0.9)
    held = generate.random_paths(lim, 4, seed=5, steps=40, hold=(2, 8))
    step = generate.random_paths(lim, 4, seed=5, steps=40)
    assert np.median(np.concatenate([_turning(k) for k in held])) < \
        0.7 * np.median(np.concatenate([_turning(k) for k in step]))
    with pytest.raises(ValueError, match="hold"):
        generate.random_motions(lim, jax.random.PRNGKey(0), 2, 4, 0.1, 24, hold=(0, 3))


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


def test_mixed_sources_written_before_the_persistent_part_regenerate_without_it():
    """A mixed config.json without ``persistent_share`` (the committed iiwa mixed set) regenerates
    with no persistent paths, whatever the current default; a recorded share is kept."""
    old = datasets.read_config("iiwa", "mixed")["source"]
    assert "persistent_share" not in old   # the committed set predates the persistent part
    params = generate.source_params("mixed", old)
    assert params["persistent_share"] == 0.0 and params["target_share"] == old["target_share"] == 0.5
    assert generate.source_params("mixed", {"target_share": 0.2, "persistent_share": 0.4}) == \
        {"target_share": 0.2, "persistent_share": 0.4}


def test_mixed_with_a_persistent_share_interleaves_the_parts_and_caps_the_spacing():
    paths, source = generate.generate_split("iiwa", "mixed", 4, 3, target_share=0.0, persistent_share=0.5)
    assert len(paths) == 4 and source["persistent_share"] == 0.5
    assert source["parts"]["persistent_random"]["hold"] == list(generate.PERSISTENT_HOLD)
    assert source["parts"]["smooth_target_point"] == {}
    for p in paths:
        assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() <= 0.3
    with pytest.raises(datasets.DatasetError, match="shares"):
        generate.generate_split("iiwa", "mixed", 2, 0, target_share=0.7, persistent_share=0.5)
