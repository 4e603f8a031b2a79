"""Reference-path datasets on disk: format, loading, statistics and import of user paths.

Layout (docs/paths.md §4, adapted)::

    splines/<robot>/<kind>/config.json     metadata (see below)
    splines/<robot>/<kind>/train.npz       one knot array [K_i, n_joints] (rad) per path
    splines/<robot>/<kind>/test.npz        same; keys "path_00000", "path_00001", ... in order

``config.json`` keys: ``format_version``, ``robot``, ``kind``, ``joint_names``, ``n_joints``,
``num_train``, ``num_test``, ``max_dis_between_knots`` (max spline arc length between consecutive
knots over all splits [rad]; it normalises observations and the reward's overshoot length),
``source`` (how the paths were made, e.g. ``{"type": "import", "file": ...}``) and any
generation parameters. Files are written atomically (temporary file + ``os.replace``).

Import: users bring paths as

* ``.npz`` -- one array ``[K, n_joints]`` per key (key order kept);
* ``.json`` -- a list of paths (each a list of knots, each a list of joint positions), or an
  object ``{name: path}``, or ``{"paths": <list or object>}``;
* ``.csv`` -- a header row and one knot per row; either only joint columns (the file is one
  path) or a first column named ``path`` whose value groups consecutive rows into paths.

Validation raises :class:`DatasetError` (a ``ValueError``) naming the path, knot and joint:
wrong joint count, NaN/inf, fewer than 2 distinct knots, knots outside the robot's position
limits.

CLI::

    python -m mjx_pathtrack.paths stats [--robot iiwa] [--kind random] [--root splines]
    python -m mjx_pathtrack.paths import FILE --robot iiwa --kind my_paths [--split test]
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path as FsPath

import numpy as np

from mjx_pathtrack.core import spline
from mjx_pathtrack.fileio import atomic_write
from mjx_pathtrack.core.limits import JointLimits

FORMAT_VERSION = 1
SPLITS = ("train", "test")
#: default dataset root: ``<repository>/splines``
DEFAULT_ROOT = FsPath(__file__).resolve().parents[2] / "splines"
#: tolerance [rad] on the position limits at import (the limits are stored as float32)
LIMIT_TOLERANCE = 1e-6


class DatasetError(ValueError):
    """Bad dataset content or layout; the message names the file/path/knot/joint."""


# ---------------------------------------------------------------------------------------------
# Robots (the registry of mjx_pathtrack.robots.registry)
# ---------------------------------------------------------------------------------------------


def robot_limits(robot: str) -> tuple[JointLimits, tuple[str, ...]]:
    """``(JointLimits, joint_names)`` of the *path joints* of a registry robot
    (:mod:`mjx_pathtrack.robots.registry`); ``DatasetError`` for an unknown one. Only position limits
    are used here."""
    from mjx_pathtrack.robots import registry as robots

    if robot not in robots.known_robots():
        raise DatasetError(f"unknown robot {robot!r}; known: {', '.join(robots.known_robots())}")
    try:
        loaded = robots.load_robot(robot)
    except ImportError as e:
        raise DatasetError(str(e)) from e
    mask = np.asarray(loaded.path_mask, bool)
    lim = loaded.limits
    pick = lambda x: np.asarray(x)[mask]  # noqa: E731
    names = tuple(n for n, m in zip(loaded.joint_names, mask) if m)
    return JointLimits(pick(lim.pos_min), pick(lim.pos_max), pick(lim.vel), pick(lim.acc), pick(lim.jerk),
                       names=names), names


def known_robots() -> tuple[str, ...]:
    from mjx_pathtrack.robots import registry as robots

    return robots.known_robots()


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------


def dataset_dir(robot: str, kind: str, root: str | os.PathLike | None = None) -> FsPath:
    """``<root>/<robot>/<kind>`` (root defaults to the repository's ``splines/``)."""
    for name, value in (("robot", robot), ("kind", kind)):
        if not value or "/" in value or "\\" in value or value.startswith("."):
            raise DatasetError(f"invalid {name} name {value!r}")
    return FsPath(DEFAULT_ROOT if root is None else root) / robot / kind


def save_split(file: str | os.PathLike, paths: Sequence[np.ndarray]) -> None:
    """Write paths (each ``[K_i, n]``) atomically to an ``.npz`` as ``path_00000``, ..."""
    arrays = {f"path_{i:05d}": np.asarray(p, np.float64) for i, p in enumerate(paths)}
    atomic_write(FsPath(file), lambda f: np.savez_compressed(f, **arrays))


def write_config(file: str | os.PathLike, config: dict) -> None:
    """Write ``config.json`` atomically (sorted keys, indented)."""
    text = json.dumps(config, indent=2, sort_keys=True) + "\n"
    atomic_write(FsPath(file), lambda f: f.write(text.encode()))


def known_kinds(robot: str, root=None) -> list[str]:
    """Names of the datasets of ``robot`` under ``root`` (folders with a ``config.json``)."""
    base = FsPath(DEFAULT_ROOT if root is None else root) / robot
    return sorted(d.name for d in base.iterdir() if (d / "config.json").is_file()) if base.is_dir() else []


def read_config(robot: str, kind: str, root=None) -> dict:
    """The dataset's ``config.json``; ``DatasetError`` if missing."""
    file = dataset_dir(robot, kind, root) / "config.json"
    if not file.is_file():
        raise DatasetError(f"no dataset config at {file}")
    return json.loads(file.read_text())


def _read_npz(file: FsPath) -> list[tuple[str, np.ndarray]]:
    with np.load(file, allow_pickle=False) as data:
        return [(key, np.asarray(data[key])) for key in data.files]


def load_split(robot: str, kind: str, split: str = "test", root=None) -> list[np.ndarray]:
    """Knot arrays ``[K_i, n_joints]`` (float64, rad) of one split, in file order."""
    if split not in SPLITS:
        raise DatasetError(f"split must be one of {SPLITS}, got {split!r}")
    file = dataset_dir(robot, kind, root) / f"{split}.npz"
    if not file.is_file():
        raise DatasetError(f"no {split} split at {file}")
    return [np.asarray(a, np.float64) for _, a in _read_npz(file)]


def load_paths(robot: str, kind: str, split: str = "test", max_knots: int | None = None,
               root=None, samples_per_segment: int = spline.SAMPLES_PER_SEGMENT) -> spline.Path:
    """The split as one stacked :class:`spline.Path` (leading axis = path index).

    ``max_knots`` defaults to the largest knot count in the split; a path with more knots
    raises ``ValueError``.
    """
    knots = load_split(robot, kind, split, root)
    if not knots:
        raise DatasetError(f"{robot}/{kind}/{split} is empty")
    return spline.stack_fits((spline.fit_spline(k, samples_per_segment) for k in knots), max_knots)


# ---------------------------------------------------------------------------------------------
# Statistics
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SplitStats:
    """Per-split summary (docs/paths.md §4 columns). Lengths in rad.

    knots, polyline_length, length: (min, mean, max) of knots per path, knot-polyline length
    and spline arc length; spacing_median / spacing_max: spline arc length between consecutive
    knots over all paths.
    """

    n_paths: int
    n_joints: int
    knots: tuple[float, float, float]
    polyline_length: tuple[float, float, float]
    length: tuple[float, float, float]
    spacing_median: float
    spacing_max: float

    def line(self, name: str) -> str:
        f3 = lambda t, fmt: "/".join(format(x, fmt) for x in t)  # noqa: E731
        return (f"{name:<28} {self.n_paths:>5} paths  {self.n_joints:>2} joints  "
                f"knots {f3(self.knots, '.0f'):<13} polyline {f3(self.polyline_length, '.1f'):<16} "
                f"arc {f3(self.length, '.1f'):<16} spacing median {self.spacing_median:.3f} "
                f"max {self.spacing_max:.3f}")


def split_stats(paths: Sequence[np.ndarray]) -> SplitStats:
    """Statistics of knot arrays ``[K_i, n]`` (each fitted as a spline for arc lengths)."""
    if not paths:
        raise DatasetError("no paths")
    fits = [spline.fit_spline(p) for p in paths]
    counts = np.array([len(p) for p in paths], float)
    poly = np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in paths])
    arc = np.array([f.length for f in fits])
    spacing = np.concatenate([np.diff(f.knot_s) for f in fits])
    mmm = lambda a: (float(a.min()), float(a.mean()), float(a.max()))  # noqa: E731
    return SplitStats(len(paths), int(paths[0].shape[1]), mmm(counts), mmm(poly), mmm(arc),
                      float(np.median(spacing)), float(spacing.max()))


def max_dis_between_knots(splits: Iterable[Sequence[np.ndarray]]) -> float:
    """Max spline arc length between consecutive knots over all given paths [rad]."""
    return max(float(np.diff(spline.fit_spline(p).knot_s).max()) for paths in splits for p in paths)


def stats(robot: str | None = None, kind: str | None = None, root=None) -> dict[str, SplitStats]:
    """Statistics of every present split under ``root``, keyed ``robot/kind/split``."""
    base = FsPath(DEFAULT_ROOT if root is None else root)
    out = {}
    for cfg in sorted(base.glob("*/*/config.json")):
        r, k = cfg.parent.parent.name, cfg.parent.name
        if (robot is None or r == robot) and (kind is None or k == kind):
            for split in SPLITS:
                if (cfg.parent / f"{split}.npz").is_file():
                    out[f"{r}/{k}/{split}"] = split_stats(load_split(r, k, split, base))
    return out


# ---------------------------------------------------------------------------------------------
# Import and validation
# ---------------------------------------------------------------------------------------------


def validate_path(knots, limits: JointLimits, joint_names: Sequence[str] | None = None,
                  name: str = "path") -> np.ndarray:
    """Check one path and return it as float64 ``[K, n]``; ``DatasetError`` names the problem."""
    lo = np.asarray(limits.pos_min, np.float64)
    hi = np.asarray(limits.pos_max, np.float64)
    n = lo.shape[0]
    names = list(joint_names) if joint_names is not None else [f"joint {j}" for j in range(n)]
    try:
        k = np.asarray(knots, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise DatasetError(f"{name}: not a numeric [K, n_joints] array ({e})") from None
    if k.ndim != 2:
        raise DatasetError(f"{name}: expected a [K, n_joints] array of knots, got shape {k.shape}")
    if k.shape[1] != n:
        raise DatasetError(f"{name}: knots have {k.shape[1]} joint values, the robot has {n} joints "
                           f"({', '.join(names)})")
    bad = np.argwhere(~np.isfinite(k))
    if bad.size:
        i, j = bad[0]
        raise DatasetError(f"{name}: knot {i}, {names[j]} is {k[i, j]} (NaN/inf not allowed)")
    distinct = 1 + int(np.sum(np.linalg.norm(np.diff(k, axis=0), axis=1) > spline.DUPLICATE_DISTANCE)) \
        if len(k) else 0
    if distinct < 2:
        raise DatasetError(f"{name}: needs at least 2 distinct knots, got {len(k)} knot(s) "
                           f"({distinct} distinct)")
    below, above = k < lo - LIMIT_TOLERANCE, k > hi + LIMIT_TOLERANCE
    bad = np.argwhere(below | above)
    if bad.size:
        i, j = bad[0]
        raise DatasetError(f"{name}: knot {i}, {names[j]} = {k[i, j]:.6g} rad is outside the position "
                           f"limits [{lo[j]:.6g}, {hi[j]:.6g}] ({len(bad)} value(s) outside in this path)")
    return k


def read_user_paths(file: str | os.PathLike) -> list[tuple[str, np.ndarray]]:
    """Read ``(name, knots)`` pairs from a user ``.npz``, ``.json`` or ``.csv`` (format above)."""
    file = FsPath(file)
    if not file.is_file():
        raise DatasetError(f"no such file: {file}")
    suffix = file.suffix.lower()
    if suffix == ".npz":
        try:
            pairs = _read_npz(file)
        except ValueError as e:   # e.g. object arrays
            raise DatasetError(f"{file}: cannot read npz ({e})") from None
    elif suffix == ".json":
        pairs = _json_paths(file)
    elif suffix == ".csv":
        pairs = _csv_paths(file)
    else:
        raise DatasetError(f"{file}: unsupported file type {suffix!r} (use .npz, .json or .csv)")
    if not pairs:
        raise DatasetError(f"{file}: contains no paths")
    return pairs


def _json_paths(file: FsPath) -> list[tuple[str, object]]:
    try:
        data = json.loads(file.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{file}: invalid JSON ({e})") from None
    if isinstance(data, dict) and "paths" in data:
        data = data["paths"]
    if isinstance(data, dict):
        return [(str(k), v) for k, v in data.items()]
    if isinstance(data, list):
        return [(f"path {i}", v) for i, v in enumerate(data)]
    raise DatasetError(f"{file}: expected a list of paths or an object of named paths")


def _csv_paths(file: FsPath) -> list[tuple[str, np.ndarray]]:
    with open(file, newline="") as f:
        rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    if len(rows) < 2:
        raise DatasetError(f"{file}: needs a header row and at least one knot row")
    header, body = [c.strip() for c in rows[0]], rows[1:]
    grouped = header[0].lower() == "path"
    order: list[str] = []
    groups: dict[str, list[list[str]]] = {}
    for line, r in enumerate(body, start=2):
        if len(r) != len(header):
            raise DatasetError(f"{file}:{line}: {len(r)} columns, header has {len(header)}")
        key = r[0].strip() if grouped else "path 0"
        if key not in groups:
            order.append(key)
            groups[key] = []
        elif grouped and order[-1] != key:
            raise DatasetError(f"{file}:{line}: rows of path {key!r} are not consecutive")
        groups[key].append(r[1:] if grouped else r)
    out = []
    for key in order:
        try:
            out.append((key if grouped else "path 0", np.array(groups[key], dtype=np.float64)))
        except ValueError as e:
            raise DatasetError(f"{file}: path {key!r}: non-numeric value ({e})") from None
    return out
