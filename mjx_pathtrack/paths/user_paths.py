"""A user's path made ready for a policy: inside the limits, knots by the policy's own rule.

Every entrance that takes a user's path (``evaluate.py --paths``, ``python -m mjx_pathtrack.paths
import``, :class:`~mjx_pathtrack.deploy.controller.OnlineTracker`) goes through :func:`prepare_path`:

1. **checked** (:func:`~mjx_pathtrack.paths.datasets.validate_path`: shape, NaN/inf, two distinct
   knots), with knots up to the robot's URDF limits accepted: the model's limits sit
   ``pos_buffer`` (0.035 rad) inside them (docs/limits.md §3), and a knot between the two is moved
   onto the model's limit. A knot beyond the URDF limits is refused, naming path, knot and joint;
2. **re-knotted** (:func:`~mjx_pathtrack.core.knot_rule.reknot`) by the knot rule of the policy's
   training data, so that the policy sees knots like its training knots whatever spacing the user
   chose (a planner's dense waypoints, sparse teach points), unless ``keep_knots``;
3. **reported**: how far each knot was moved into the limits, and the largest distance between
   the user's curve and the curve the policy is given (joint space [rad] and, with ``fk``, of the
   target points [m]).

The user's curve (the natural cubic spline through the knots as given, moved inside the limits)
stays what evaluation measures the deviation against (:attr:`PreparedPath.given`).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path as FsPath
from types import SimpleNamespace

import numpy as np

from mjx_pathtrack.core.joint_limits import JointLimits
from mjx_pathtrack.core.knot_rule import KnotRule, curve_distance, reknot
from mjx_pathtrack.paths import datasets as D
from mjx_pathtrack.paths.datasets import LIMIT_TOLERANCE, DatasetError, validate_path


@dataclasses.dataclass(frozen=True)
class PreparedPath:
    """One user path, ready for a policy.

    name; given ``[K, n]``: the user's knots moved inside the model's limits (the user's curve);
    knots ``[K', n]``: the knots the policy is given (``given`` itself with ``keep_knots``);
    limit_shift [rad]: the largest move of a knot into the limits (0: none needed);
    joint_distance [rad] / cartesian_distance [m] (None without FK): the largest distance
    between the user's curve and the curve through ``knots``.
    """

    name: str
    given: np.ndarray
    knots: np.ndarray
    limit_shift: float
    joint_distance: float
    cartesian_distance: float | None

    def summary(self) -> dict:
        return {"name": self.name, "knots_given": len(self.given), "knots": len(self.knots),
                "limit_shift_rad": self.limit_shift, "curve_distance_rad": self.joint_distance,
                "curve_distance_m": self.cartesian_distance}


def into_limits(knots, limits: JointLimits, allowance: float, joint_names: Sequence[str] | None = None,
                name: str = "path") -> tuple[np.ndarray, float]:
    """``(knots', shift)``: ``knots [K, n]`` with every value up to ``allowance`` [rad] beyond a
    position limit moved onto it (``shift``: the largest move [rad]); :class:`DatasetError`
    naming path, knot and joint for a value further out."""
    lo = np.asarray(limits.pos_min, np.float64)
    hi = np.asarray(limits.pos_max, np.float64)
    k = np.asarray(knots, np.float64)
    names = list(joint_names) if joint_names is not None else [f"joint {j}" for j in range(k.shape[1])]
    far = np.argwhere((k < lo - allowance - LIMIT_TOLERANCE) | (k > hi + allowance + LIMIT_TOLERANCE))
    if far.size:
        i, j = far[0]
        raise DatasetError(f"{name}: knot {i}, {names[j]} = {k[i, j]:.6g} rad is beyond the robot's limits "
                           f"[{lo[j] - allowance:.6g}, {hi[j] + allowance:.6g}] (the model's "
                           f"[{lo[j]:.6g}, {hi[j]:.6g}] plus its {allowance:g} rad safety buffer; "
                           f"{len(far)} value(s) beyond in this path)")
    clipped = np.clip(k, lo, hi)
    return clipped, float(np.max(np.abs(clipped - k), initial=0.0))


def prepare_path(knots, limits: JointLimits, rule: KnotRule | None, joint_names: Sequence[str] | None = None,
                 name: str = "path", allowance: float = 0.0, fk: Callable | None = None,
                 distance_step: float = 2e-3, start_slope=None) -> PreparedPath:
    """Check, move inside the limits and re-knot one user path (module docstring).

    ``limits``: the path joints' (model) limits; ``rule``: the policy's knot rule (None: keep the
    knots as given); ``allowance`` [rad]: how far beyond the limits a knot may lie and still be
    moved onto them (the robot's URDF-to-model buffer); ``fk(q [P, n_path]) -> [P, T, 3]``: target
    points for the Cartesian distance; ``start_slope [n]``: the curve starts with this derivative
    (a path continued during motion, :func:`~mjx_pathtrack.core.spline.replace_ahead`) instead of a
    natural start. Raises :class:`DatasetError` naming the problem."""
    unbounded = np.full(np.shape(limits.pos_min), np.inf)   # the limits are into_limits' to check
    raw = validate_path(knots, SimpleNamespace(pos_min=-unbounded, pos_max=unbounded), joint_names, name=name)
    given, shift = into_limits(raw, limits, allowance, joint_names, name)
    if rule is None:
        return PreparedPath(name, given, given, shift, 0.0, 0.0 if fk is not None else None)
    try:
        out = reknot(given, rule, start_slope)
    except ValueError as e:
        raise DatasetError(f"{name}: {e}") from None
    # the rule's knots lie on the user's curve, which can bulge past a limit between two knots
    out, _ = into_limits(out, limits, np.inf)
    joint, cart = curve_distance(given, out, distance_step, fk, start_slope)
    return PreparedPath(name, given, out, shift, joint, cart)


def prepare_paths(named_knots, limits: JointLimits, rule: KnotRule | None, joint_names=None, allowance: float = 0.0,
                  fk: Callable | None = None, prefix: str = "") -> list[PreparedPath]:
    """:func:`prepare_path` of every ``(name, knots)`` pair (names prefixed by ``prefix``)."""
    return [prepare_path(k, limits, rule, joint_names, f"{prefix}{name}", allowance, fk) for name, k in named_knots]


def report_lines(prepared: Sequence[PreparedPath], rule: KnotRule | None) -> list[str]:
    """Human-readable summary of a batch of prepared paths (what ``evaluate.py`` and ``import`` print)."""
    n = len(prepared)
    moved = [p for p in prepared if p.limit_shift > 0]
    lines = []
    if moved:
        worst = max(moved, key=lambda p: p.limit_shift)
        lines.append(f"{len(moved)} of {n} path(s) had knots beyond the model's position limits (within the URDF's): "
                     f"moved onto them by up to {worst.limit_shift:.4f} rad ({worst.name})")
    if rule is None:
        lines.append(f"{n} path(s) tracked with their knots as given (--keep-knots)")
        return lines
    given = np.array([len(p.given) for p in prepared])
    ours = np.array([len(p.knots) for p in prepared])
    joint = np.array([p.joint_distance for p in prepared])
    how = (f"curvature {rule.curvature_distance:g} after {rule.resampling_distance:g} rad" if rule.curvature_distance
           else f"every {rule.resampling_distance:g} rad")
    cap = f", at most {rule.max_spacing:.3f} rad apart" if rule.max_spacing else ""
    lines.append(f"{n} path(s) re-knotted by the policy's knot rule ({how}{cap}): knots per path given "
                 f"{given.mean():.1f}, policy's {ours.mean():.1f}")
    text = (f"largest distance between your curve and the policy's: joint {joint.max():.4f} rad "
            f"(median over paths {np.median(joint):.4f})")
    cart = [p.cartesian_distance for p in prepared if p.cartesian_distance is not None]
    if cart:
        text += f", target point {100 * max(cart):.2f} cm (median {100 * np.median(cart):.2f})"
    lines.append(text + "; deviations below are measured against your curve")
    return lines


def import_paths(file: str | os.PathLike, robot: str, kind: str, split: str = "test", root=None,
                 limits: JointLimits | None = None, joint_names: Sequence[str] | None = None,
                 overwrite: bool = False, rule=None, allowance: float = 0.0, cartesian: bool = False,
                 q_start=None) -> FsPath:
    """Validate user paths and write them as ``<root>/<robot>/<kind>/<split>.npz``.

    ``cartesian``: the file holds tool positions ``[W, 3]`` [m] per path instead of joint knots;
    each becomes its joint path by IK (:func:`~mjx_pathtrack.paths.cartesian.tool_path_to_joints`,
    from ``q_start [n]`` if given), and the largest IK residual is recorded under ``source``.

    ``limits``/``joint_names`` default to :func:`~mjx_pathtrack.paths.datasets.robot_limits`; knots up to ``allowance`` [rad]
    beyond the limits are moved onto them; ``rule`` (a
    :class:`~mjx_pathtrack.core.knot_rule.KnotRule`): the paths are re-knotted by it
    (:func:`prepare_paths`; None: kept as given). Updates ``config.json`` (counts,
    ``max_dis_between_knots`` over all present splits, the rule and the largest curve distance
    and limit move per path under ``source``). Refuses to replace an existing split unless
    ``overwrite``. Returns the dataset directory.
    """
    if split not in D.SPLITS:
        raise DatasetError(f"split must be one of {D.SPLITS}, got {split!r}")
    if limits is None:
        limits, default_names = D.robot_limits(robot)
        joint_names = default_names if joint_names is None else joint_names
    directory = D.dataset_dir(robot, kind, root)
    target = directory / f"{split}.npz"
    if target.exists() and not overwrite:
        raise DatasetError(f"{target} exists (use overwrite=True / --overwrite to replace it)")
    pairs, ik_info = D.read_user_paths(file), None
    if cartesian:
        from mjx_pathtrack.paths.cartesian import tool_paths_to_joints
        from mjx_pathtrack.robots import registry as robots

        converted = tool_paths_to_joints(robots.load_robot(robot), pairs, q_start)
        pairs = [(c.name, c.joints) for c in converted]
        ik_info = {"ik_residual_mm_max": 1000 * max(float(c.residual.max()) for c in converted),
                   "ik_points": int(sum(len(c.joints) for c in converted)),
                   "report": [c.report_line() for c in converted]}
    prepared = prepare_paths(pairs, limits, rule, joint_names, allowance=allowance,
                             prefix=f"{FsPath(file).name}: ")
    paths = [p.knots for p in prepared]

    cfg_file = directory / "config.json"
    config = json.loads(cfg_file.read_text()) if cfg_file.is_file() else {}
    n = paths[0].shape[1]
    if config.get("n_joints", n) != n:
        raise DatasetError(f"{directory}: existing splits have {config['n_joints']} joints, new paths {n}")
    D.save_split(target, paths)
    splits = {s: (paths if s == split else D.load_split(robot, kind, s, root))
              for s in D.SPLITS if s == split or (directory / f"{s}.npz").is_file()}
    config.update(
        format_version=D.FORMAT_VERSION, robot=robot, kind=kind, n_joints=n,
        joint_names=list(joint_names) if joint_names is not None else config.get("joint_names"),
        max_dis_between_knots=D.max_dis_between_knots(splits.values()),
        **{f"num_{s}": len(splits.get(s, ())) for s in D.SPLITS})
    config.setdefault("source", {})[split] = {
        "type": "import", "file": FsPath(file).name, "knot_rule": None if rule is None else rule.to_json(),
        "curve_distance_rad_max": max(p.joint_distance for p in prepared),
        "limit_shift_rad_max": max(p.limit_shift for p in prepared),
        **({} if ik_info is None else {"cartesian": ik_info})}
    D.write_config(cfg_file, config)
    return directory
