"""Atomic writes leave either the old file or the complete new one, never a partial file."""

import json
import os
import stat

import pytest

from mjx_pathtrack.fileio import atomic_write, atomic_write_bytes


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
