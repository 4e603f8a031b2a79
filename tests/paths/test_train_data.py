"""Regeneration of a larger train split for a run (deterministic, into the run's data dir)."""

import json

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401

from mjx_pathtrack.paths import datasets
from mjx_pathtrack.paths import generate
from mjx_pathtrack.paths.train_data import ensure_train_paths


def test_missing_train_paths_are_regenerated_deterministically(tmp_path):
    root, data = tmp_path / "splines", tmp_path / "run" / "data"
    generate.generate_dataset("iiwa", "target_point", num_train=0, num_test=2, seed=5, root=root, steps=12)
    config = datasets.read_config("iiwa", "target_point", root)
    assert config["source"]["seed"] == 5 and config["source"]["steps"] == 12 and config["num_test"] == 2

    assert ensure_train_paths("iiwa", "target_point", 0, root, data) == root      # nothing asked
    with pytest.raises(datasets.DatasetError, match="no data directory"):
        ensure_train_paths("iiwa", "target_point", 2, root, None)

    logs = []
    assert ensure_train_paths("iiwa", "target_point", 2, root, data, log=logs.append) == data
    assert any("regenerating 2" in line for line in logs)
    train = datasets.load_split("iiwa", "target_point", "train", data)
    assert len(train) == 2
    # the copied test split and the original observation scale come along
    test = datasets.load_split("iiwa", "target_point", "test", data)
    for x, y in zip(test, datasets.load_split("iiwa", "target_point", "test", root)):
        np.testing.assert_array_equal(x, y)
    saved = json.loads((data / "iiwa" / "target_point" / "config.json").read_text())
    assert saved["max_dis_between_knots"] == config["max_dis_between_knots"] and saved["num_train"] == 2

    # deterministic: the train split is the generator's output for the dataset's own seed
    expected, _ = generate.generate_split("iiwa", "target_point", 2, 5, steps=12)
    for x, y in zip(train, expected):
        np.testing.assert_array_equal(x, y)

    logs.clear()
    assert ensure_train_paths("iiwa", "target_point", 2, root, data, log=logs.append) == data
    assert any("reusing" in line for line in logs)
