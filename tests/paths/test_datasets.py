"""Tests of mjx_pathtrack.paths.datasets: on-disk format, loading, stats, import and its errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import mjx_pathtrack  # noqa: F401  (XLA flags before jax)

import numpy as np
import pytest

from mjx_pathtrack.paths import datasets as D
from mjx_pathtrack.paths.user_paths import import_paths
from mjx_pathtrack.robots import iiwa
from mjx_pathtrack.core import spline

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def iiwa_paths(n: int, seed: int = 0) -> list[np.ndarray]:
    """Smooth random paths inside the iiwa limits, 20..40 knots each."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        k = rng.integers(20, 41)
        x = np.linspace(0, 1, k)[:, None]
        phase, freq = rng.uniform(0, 6.3, 7), rng.uniform(0.5, 2.0, 7)
        out.append(0.6 * iiwa.POS * np.sin(2 * np.pi * freq * x + phase))
    return out


def write_npz(tmp_path, paths, name="user.npz"):
    file = tmp_path / name
    np.savez(file, **{f"p{i}": p for i, p in enumerate(paths)})
    return file


def test_save_load_roundtrip_and_load_paths(tmp_path):
    paths = iiwa_paths(5)
    file = tmp_path / "iiwa" / "demo" / "test.npz"
    D.save_split(file, paths)
    assert not [f for f in os.listdir(file.parent) if f.endswith(".tmp")]   # no temp file left
    loaded = D.load_split("iiwa", "demo", "test", root=tmp_path)
    assert len(loaded) == 5
    for a, b in zip(paths, loaded):
        np.testing.assert_array_equal(a, b)
    batch = D.load_paths("iiwa", "demo", "test", root=tmp_path)
    kmax = max(len(p) for p in paths)
    assert batch.knots.shape == (5, kmax, 7)
    np.testing.assert_array_equal(batch.n_knots, [len(p) for p in paths])
    np.testing.assert_allclose(batch.length, [spline.fit_spline(p).length for p in paths], rtol=1e-6)
    with pytest.raises(ValueError, match="max_knots"):
        D.load_paths("iiwa", "demo", "test", max_knots=10, root=tmp_path)
    with pytest.raises(D.DatasetError, match="no train split"):
        D.load_split("iiwa", "demo", "train", root=tmp_path)


def test_import_npz_writes_split_and_config(tmp_path):
    paths = iiwa_paths(4)
    directory = import_paths(write_npz(tmp_path, paths), "iiwa", "mine", "test", root=tmp_path / "s")
    config = json.loads((directory / "config.json").read_text())
    assert config["num_test"] == 4 and config["num_train"] == 0
    assert config["n_joints"] == 7 and config["joint_names"] == list(iiwa.JOINT_NAMES)
    expected = max(np.diff(spline.fit_spline(p).knot_s).max() for p in paths)
    assert config["max_dis_between_knots"] == pytest.approx(expected)
    with pytest.raises(D.DatasetError, match="exists"):
        import_paths(write_npz(tmp_path, paths), "iiwa", "mine", "test", root=tmp_path / "s")
    # a train split next to it updates counts and the max spacing over both splits
    big = [np.concatenate([paths[0][:2], paths[0][-1:]])]
    import_paths(write_npz(tmp_path, big, "b.npz"), "iiwa", "mine", "train", root=tmp_path / "s")
    config = json.loads((directory / "config.json").read_text())
    assert config["num_train"] == 1 and config["num_test"] == 4
    assert config["max_dis_between_knots"] > expected


def test_import_json_and_csv(tmp_path):
    paths = iiwa_paths(2)
    jfile = tmp_path / "u.json"
    jfile.write_text(json.dumps({"paths": {"a": paths[0].tolist(), "b": paths[1].tolist()}}))
    import_paths(jfile, "iiwa", "j", root=tmp_path)
    for a, b in zip(paths, D.load_split("iiwa", "j", root=tmp_path)):
        np.testing.assert_allclose(a, b, rtol=1e-15)

    cfile = tmp_path / "u.csv"
    lines = ["path," + ",".join(iiwa.JOINT_NAMES)]
    for name, p in zip("xy", paths):
        lines += [name + "," + ",".join(repr(float(v)) for v in row) for row in p]
    cfile.write_text("\n".join(lines) + "\n")
    import_paths(cfile, "iiwa", "c", root=tmp_path)
    for a, b in zip(paths, D.load_split("iiwa", "c", root=tmp_path)):
        np.testing.assert_allclose(a, b, rtol=1e-15)

    single = tmp_path / "one.csv"
    single.write_text("\n".join([",".join(iiwa.JOINT_NAMES)]
                                + [",".join(repr(float(v)) for v in row) for row in paths[0]]))
    assert len(D.read_user_paths(single)) == 1


@pytest.mark.parametrize("make, message", [
    (lambda p: p[:, :6], r"6 joint values, the robot has 7 joints"),
    (lambda p: np.where(np.arange(len(p))[:, None] == 3, np.nan, p), r"knot 3, iiwa_joint_1 is nan"),
    (lambda p: p[:1], r"at least 2 distinct knots, got 1 knot"),
    (lambda p: np.repeat(p[:1], 5, 0), r"at least 2 distinct knots, got 5 knot\(s\) \(1 distinct\)"),
    (lambda p: np.where((np.arange(len(p)) == 2)[:, None] & (np.arange(7) == 1), 2.5, p),
     r"knot 2, iiwa_joint_2 = 2.5 rad is beyond the robot.s limits \[-2.0594, 2.0594\]"),
    (lambda p: p[None], r"expected a \[K, n_joints\] array"),
])
def test_import_errors(tmp_path, make, message):
    good = iiwa_paths(2)
    file = write_npz(tmp_path, [good[0], make(good[1])])
    with pytest.raises(D.DatasetError, match=message) as info:
        import_paths(file, "iiwa", "bad", root=tmp_path)
    assert "user.npz: p1" in str(info.value)
    assert not (tmp_path / "iiwa" / "bad").exists()      # nothing written on error


@pytest.mark.parametrize("name, content, message", [
    ("x.txt", "1,2", "unsupported file type"),
    ("bad.json", "{", "invalid JSON"),
    ("cols.csv", "a,b\n1,2,3\n", r"cols.csv:2: 3 columns, header has 2"),
    ("split.csv", "path,a\nx,1\ny,2\nx,3\n", "not consecutive"),
    ("word.csv", "a,b\n1,zz\n", "non-numeric"),
])
def test_read_user_paths_errors(tmp_path, name, content, message):
    (tmp_path / name).write_text(content)
    with pytest.raises(D.DatasetError, match=message):
        D.read_user_paths(tmp_path / name)


def test_import_file_errors(tmp_path):
    with pytest.raises(D.DatasetError, match="no such file"):
        D.read_user_paths(tmp_path / "missing.npz")
    (tmp_path / "ragged.json").write_text(json.dumps([[[0.0] * 7, [0.1] * 6]]))
    with pytest.raises(D.DatasetError, match="not a numeric"):
        import_paths(tmp_path / "ragged.json", "iiwa", "r", root=tmp_path)
    with pytest.raises(D.DatasetError, match="unknown robot 'ur5'"):
        import_paths(write_npz(tmp_path, iiwa_paths(1)), "ur5", "x", root=tmp_path)
    with pytest.raises(D.DatasetError, match="invalid kind"):
        D.dataset_dir("iiwa", "../x", tmp_path)


def test_split_stats_values():
    # two straight paths with known lengths and spacings
    a = np.outer(np.array([0.0, 0.1, 0.2, 0.5]), np.ones(7) / np.sqrt(7))
    b = np.outer(np.array([0.0, 1.0, 2.0]), np.ones(7) / np.sqrt(7))
    st = D.split_stats([a, b])
    assert st.n_paths == 2 and st.n_joints == 7
    assert st.knots == (3.0, 3.5, 4.0)
    assert st.polyline_length == pytest.approx((0.5, 1.25, 2.0))
    assert st.length == pytest.approx((0.5, 1.25, 2.0))
    assert st.spacing_median == pytest.approx(np.median([0.1, 0.1, 0.3, 1.0, 1.0]))
    assert st.spacing_max == pytest.approx(1.0)


def test_cli_import_and_stats(tmp_path):
    file = write_npz(tmp_path, iiwa_paths(3))
    env = dict(os.environ, PYTHONPATH=REPO, JAX_PLATFORMS="cpu")
    run = lambda *a: subprocess.run([sys.executable, "-m", "mjx_pathtrack.paths", *a],  # noqa: E731
                                    capture_output=True, text=True, env=env, cwd=tmp_path)
    root = str(tmp_path / "s")
    out = run("import", str(file), "--robot", "iiwa", "--kind", "demo", "--root", root)
    assert out.returncode == 0, out.stderr
    assert "iiwa/demo/test" in out.stdout and "3 paths" in out.stdout
    assert "re-knotted by the rule of iiwa/mixed" in out.stdout
    cfg = D.read_config("iiwa", "demo", root)
    assert cfg["source"]["test"]["knot_rule"]["max_spacing"] == pytest.approx(
        D.read_config("iiwa", "mixed")["max_dis_between_knots"])
    assert cfg["max_dis_between_knots"] <= cfg["source"]["test"]["knot_rule"]["max_spacing"] + 1e-9
    out = run("import", str(file), "--robot", "iiwa", "--kind", "kept", "--root", root, "--keep-knots")
    assert out.returncode == 0, out.stderr
    for given, stored in zip(iiwa_paths(3), D.load_split("iiwa", "kept", "test", root)):
        np.testing.assert_array_equal(given, stored)
    out = run("stats", "--root", root)
    assert out.returncode == 0 and "iiwa/demo/test" in out.stdout and "spacing median" in out.stdout
    bad = write_npz(tmp_path, [iiwa_paths(1)[0][:, :5]], "bad.npz")
    out = run("import", str(bad), "--robot", "iiwa", "--kind", "bad", "--root", root)
    assert out.returncode == 2 and "5 joint values, the robot has 7 joints" in out.stderr
