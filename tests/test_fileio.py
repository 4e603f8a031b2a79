"""Atomic writes leave either the old file or the complete new one, never a partial file."""

import csv
import json
import os
import stat

import pytest

from mjx_pathtrack.fileio import append_csv_row, atomic_write, atomic_write_bytes


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    file = tmp_path / "x" / "config.json"
    atomic_write_bytes(file, json.dumps({"a": 1}).encode())

    def boom(f):
        f.write(b"partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(file, boom)
    assert json.loads(file.read_text()) == {"a": 1}
    assert os.listdir(file.parent) == ["config.json"]


def test_atomic_write_replaces_and_is_readable_by_others(tmp_path):
    file = tmp_path / "data.bin"
    atomic_write_bytes(file, b"one")
    atomic_write_bytes(file, b"two")
    assert file.read_bytes() == b"two"
    assert stat.S_IMODE(file.stat().st_mode) == 0o644


def test_append_csv_row_keeps_columns_aligned_when_keys_change(tmp_path):
    log = tmp_path / "progress.csv"
    append_csv_row(log, {"step": 0, "eval/return": 1.5})
    append_csv_row(log, {"step": 10, "training/loss": 0.25, "eval/return": 2.5})
    append_csv_row(log, {"step": 20, "eval/return": 3.5})
    with open(log, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["step", "eval/return", "training/loss"]
    assert [r["eval/return"] for r in rows] == ["1.5", "2.5", "3.5"]
    assert [r["training/loss"] for r in rows] == ["", "0.25", ""]
    assert not [p for p in tmp_path.iterdir() if p.name != "progress.csv"]  # no temp files left
