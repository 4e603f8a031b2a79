"""The sweep file: its fields (:class:`SweepSpec`), parsing with errors that name the bad field,
the grid's points (:class:`Point`, the Cartesian product of ``grid`` over ``base``) and the
checks made before anything trains. The file format is described in :mod:`mjx_pathtrack.sweeps.run`.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path as FsPath
from typing import Any, Sequence

import numpy as np

from mjx_pathtrack.config.run import FLAT_NAMES, TrainConfig


SPEC_KEYS = ("base", "grid", "test_datasets", "eval_episodes", "eval_seed", "vectorize", "out")


class SweepError(ValueError):
    """A bad sweep file or an output directory that does not fit it; the message says why."""


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep file: ``base`` and ``grid`` (field -> tuple of values) over
    :class:`~mjx_pathtrack.config.run.TrainConfig`, extra test datasets and evaluation settings."""

    base: dict
    grid: dict
    test_datasets: tuple[str, ...] = ()
    eval_episodes: int = 64
    eval_seed: int = 0
    vectorize: bool = True
    out: str | None = None


@dataclasses.dataclass(frozen=True)
class Point:
    """One grid point: its directory name, swept values and full training config."""

    name: str
    values: dict
    config: TrainConfig


def _coerce(field: str, value: Any, where: str) -> Any:
    """``value`` as the type of TrainConfig option ``field`` (a flat name or dotted path);
    :class:`SweepError` if it is not."""
    default = TrainConfig().get(field)
    bad = SweepError(f"{where}: {field} = {value!r} is not a valid {type(default).__name__ if default is not None else 'path'}")
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad
        return value
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or not value or not all(isinstance(v, int) and not isinstance(v, bool)
                                                                        and v > 0 for v in value):
            raise SweepError(f"{where}: {field} = {value!r} must be a list of positive layer sizes")
        return tuple(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise bad
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if isinstance(default, str) or default is None:
        if not isinstance(value, str) and not (default is None and value is None):
            raise bad
        return value
    raise bad


def _known(name: str) -> bool:
    """Whether ``name`` is a TrainConfig option (flat name or dotted path to a leaf)."""
    try:
        return not dataclasses.is_dataclass(TrainConfig().get(name))
    except (ValueError, AttributeError):
        return False


def parse_spec(data: Any, source: str = "sweep file") -> SweepSpec:
    """Validate a loaded sweep mapping (see the module docstring); :class:`SweepError` naming the
    offending key otherwise."""
    fields = list(FLAT_NAMES)
    if not isinstance(data, dict):
        raise SweepError(f"{source}: expected a mapping with keys {', '.join(SPEC_KEYS)}, got {type(data).__name__}")
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise SweepError(f"{source}: unknown key(s) {unknown}; known: {', '.join(SPEC_KEYS)}")
    base, grid = data.get("base") or {}, data.get("grid") or {}
    for name, section in (("base", base), ("grid", grid)):
        if not isinstance(section, dict):
            raise SweepError(f"{source}: '{name}' must be a mapping of TrainConfig fields")
        wrong = sorted(k for k in section if not _known(k))
        if wrong:
            raise SweepError(f"{source}: {name}: unknown TrainConfig field(s) {wrong}; known: {', '.join(fields)} "
                             f"or a dotted path (env.substeps)")
    both = sorted(set(base) & set(grid))
    if both:
        raise SweepError(f"{source}: field(s) {both} are in both base and grid")
    base = {k: _coerce(k, v, f"{source}: base") for k, v in base.items()}
    parsed_grid = {}
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise SweepError(f"{source}: grid: {key} must be a non-empty list of values, got {values!r}")
        coerced = tuple(_coerce(key, v, f"{source}: grid") for v in values)
        if len(set(coerced)) != len(coerced):
            raise SweepError(f"{source}: grid: {key} has duplicate values {list(values)}")
        parsed_grid[key] = coerced
    tests = data.get("test_datasets") or []
    if isinstance(tests, str):
        tests = [tests]
    if not isinstance(tests, list) or not all(isinstance(t, str) and t for t in tests):
        raise SweepError(f"{source}: test_datasets must be a list of dataset names, got {tests!r}")
    episodes, seed, vectorize = data.get("eval_episodes", 64), data.get("eval_seed", 0), data.get("vectorize", True)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise SweepError(f"{source}: eval_episodes must be a positive integer, got {episodes!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise SweepError(f"{source}: eval_seed must be an integer, got {seed!r}")
    if not isinstance(vectorize, bool):
        raise SweepError(f"{source}: vectorize must be true or false, got {vectorize!r}")
    out = data.get("out")
    if out is not None and not isinstance(out, str):
        raise SweepError(f"{source}: out must be a directory path, got {out!r}")
    return SweepSpec(base, parsed_grid, tuple(tests), episodes, seed, vectorize, out)


def load_spec(file: str | FsPath) -> SweepSpec:
    """Read and validate a YAML sweep file."""
    import yaml

    file = FsPath(file)
    if not file.is_file():
        raise SweepError(f"no sweep file at {file}")
    try:
        data = yaml.safe_load(file.read_text())
    except yaml.YAMLError as e:
        raise SweepError(f"{file}: invalid YAML: {e}") from None
    return parse_spec(data, str(file))


def _label(value: Any) -> str:
    if isinstance(value, tuple):
        return "x".join(map(str, value))
    return str(value).replace("/", "-").replace(" ", "")


def grid_points(spec: SweepSpec) -> list[Point]:
    """The Cartesian product of the grid over the base config, in file order (last key fastest)."""
    keys = list(spec.grid)
    points = []
    for combo in itertools.product(*(spec.grid[k] for k in keys)):
        values = dict(zip(keys, combo))
        try:
            config = TrainConfig.from_flat({**spec.base, **values})
        except (TypeError, ValueError) as e:  # pragma: no cover - fields were validated
            raise SweepError(str(e)) from None
        name = "_".join(f"{k}={_label(v)}" for k, v in values.items()) or "base"
        points.append(Point(name, values, config))
    return points


def steps_mjx_physics(file: str | FsPath) -> bool:
    """Whether a point of the sweep file ``file`` steps MJX physics (an executor other than
    ``kinematic``), i.e. whether the process needs the CPU fusion-emitter flag
    (``mjx_pathtrack.prepare_xla``); kinematic points train faster without it. True if the file
    cannot be read (the sweep itself then reports why)."""
    try:
        return any(p.config.executor != "kinematic" for p in grid_points(load_spec(file)))
    except (OSError, ValueError):
        return True


def check_datasets(spec: SweepSpec, points: Sequence[Point]) -> None:
    """Fail before any training if a training or test dataset is missing."""
    from mjx_pathtrack.paths import datasets

    needed = {(p.config.robot, p.config.dataset, p.config.dataset_root) for p in points}
    needed |= {(p.config.robot, name, p.config.dataset_root) for p in points for name in spec.test_datasets}
    for robot, kind, root in sorted(needed, key=str):
        for split in ("train", "test"):
            file = datasets.dataset_dir(robot, kind, root) / f"{split}.npz"
            if not file.is_file():
                raise SweepError(f"dataset {robot}/{kind}: no {split} split at {file} (generate it with "
                                 f"python -m mjx_pathtrack.paths generate --robot {robot} --kind {kind})")
