"""Atomic file writes: a temporary file in the target directory, fsync, then ``os.replace``.

A reader never sees a half-written file, and a crash leaves the old file (or none) in place.
"""

from __future__ import annotations

import csv
import io
import math
import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None], mode: int = 0o644) -> None:
    """Create/replace ``path`` with what ``write(file)`` writes (parent folders are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """:func:`atomic_write` of ``data``."""
    atomic_write(path, lambda f: f.write(data))


def append_csv_row(path: str | os.PathLike, row: dict[str, Any]) -> None:
    """Append ``row`` to the CSV log ``path``, rewriting it atomically.

    Rows may bring keys the earlier rows lacked (e.g. training metrics that appear only after
    the first evaluation): the header becomes the union of all keys in order of first
    appearance and every row keeps its values under its own columns (missing cells empty), so
    a log never has values shifted under the wrong header.
    """
    path = Path(path)
    rows: list[dict[str, Any]] = []
    if path.exists():
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    rows.append(row)
    fields: dict[str, None] = {}
    for r in rows:
        fields.update(dict.fromkeys(r))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(fields), restval="")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, text.getvalue().encode())


def json_safe(value):
    """``value`` with NaN/inf floats replaced by None (strict JSON)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
