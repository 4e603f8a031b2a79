"""Generalisation benchmark: deployed policies on path families they never trained on.

    python benchmarks/generalisation.py runs/iiwa_random/export                 # every family, 100 paths each
    python benchmarks/generalisation.py RUN_OR_EXPORT ... --count 50 --families planner_dense teach_points
    python benchmarks/generalisation.py runs/iiwa_random --stochastic           # the sampled policy (run dirs)

Rows, per policy (``evaluate.py``'s machinery, deterministic policy unless ``--stochastic``):

* ``own test split``: the policy's training dataset's test split, random sub-paths (seed 0), knots
  as generated -- the in-distribution reference;
* ``one curve, any knots``: whole paths of the own test split (the first ``--count``) with their
  knots as generated (kept, and re-knotted as every entrance does), and the same curves given
  again with waypoints every 0.03 rad (a motion planner's), every third of those, and re-spaced
  uniformly every 0.15 rad, each re-knotted: end reached and duration ratio must not depend on
  where the knots sat (within 1 point and 3 % of the re-knotted own knots);
* every other dataset of the robot under ``splines/`` (e.g. ``target_point`` for a random-path
  policy), given as user paths: re-knotted by the policy's rule, random sub-paths (seed 0);
* the families of :mod:`mjx_pathtrack.paths.families` (Cartesian seams and circles through IK,
  pick-and-place teach points, planner-dense waypoints, sparse teach points, paths on the
  limits), made by generators independent of the training ones and given as user paths
  (``evaluate.py --paths``): whole paths, re-knotted, deviations measured against the user's curve.

A ball-on-plate policy gets its own test split (whole paths) and the ball families instead
(``level_plate``: an independent tray-path generator anywhere in the workspace;
``papers_ball_region``: the papers' start region with its reflections), in the full-arm MJX
scene (``--ball-physics``), with the ball's falls against ``--max-falls-own`` / ``--max-falls``.

Per row: end reached, ends on the deviation limit, duration ratio to TOPP-RA (``--jerk-optimum``:
also TOPP3), joint deviation mean / max / final, Cartesian mean, the largest distance between
the user's curve and the policy's (re-knotting), and the limit audit. The floors of the issue
"Any path a user brings" are checked (``--min-end``, ``--min-end-own``, ``--max-ratio``) and the
exit status is 1 if one is missed. Writes ``generalisation.json`` and ``generalisation.md`` to
``--out`` (default ``benchmarks/results/generalisation``); the generated family files are kept in
``--out/paths`` and reused.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the FK and IK of the families run MJX kinematics

REPO = Path(__file__).resolve().parents[1]
#: datasets whose test split is the policy's "own kind" (floor --min-end-own)
OWN_KINDS = ("random", "target_point")


def parse_args(argv=None):
    from mjx_pathtrack.paths.families import BALL_FAMILIES, FAMILIES

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("sources", nargs="+", metavar="RUN_OR_EXPORT")
    p.add_argument("--families", nargs="+", default=None, choices=list(FAMILIES) + list(BALL_FAMILIES),
                   help="default: every family of the policy's task (ball on plate: the level-plate ones)")
    p.add_argument("--no-datasets", action="store_true", help="skip the robot's other datasets")
    p.add_argument("--no-respaced", action="store_true", help="skip the 'one curve, any knots' rows")
    p.add_argument("--count", type=int, default=100, help="paths per family")
    p.add_argument("--seed", type=int, default=12345, help="family generation (independent of the datasets' seeds)")
    p.add_argument("--stochastic", action="store_true", help="sampled actions (run directories only)")
    p.add_argument("--jerk-optimum", action="store_true", help="also the TOPP3 ratio (copp-py; slow the first time)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--min-end", type=float, default=0.95, help="floor of end reached on every family")
    p.add_argument("--min-end-own", type=float, default=0.98, help="floor on the random and target-point datasets")
    p.add_argument("--max-ratio", type=float, default=1.35, help="floor of the mean duration ratio to TOPP-RA")
    p.add_argument("--max-falls-own", type=float, default=0.01, help="ball on plate: falls on its own test paths")
    p.add_argument("--max-falls", type=float, default=0.02, help="ball on plate: falls on every other row")
    p.add_argument("--ball-physics", default="arm", choices=("arm", "plate", "rolling"),
                   help="ball on plate: the scene of every row (default the full-arm MJX scene)")
    p.add_argument("--terminate-deviation", type=float, default=None, metavar="RAD",
                   help="end episodes at this deviation instead of the training config's (compare policies "
                        "trained with other limits at one bar)")
    p.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "generalisation"))
    args = p.parse_args(argv)
    if args.count < 1:
        p.error(f"--count must be >= 1, got {args.count}")
    if args.terminate_deviation is not None and not args.terminate_deviation > 0:
        p.error(f"--terminate-deviation must be a number > 0, got {args.terminate_deviation}")
    for s in args.sources:
        if not Path(s).is_dir():
            p.error(f"no run or export directory at {s}")
    return args


def family_file(out: Path, robot, family: str, count: int, seed: int) -> Path:
    """The family's paths as a user path file (generated once, then reused)."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.paths.families import BALL_FAMILIES, FAMILIES

    file = out / "paths" / f"{robot.name}_{family}_{count}_{seed}.npz"
    if not file.is_file():
        t = time.time()
        datasets.save_split(file, {**FAMILIES, **BALL_FAMILIES}[family](robot, count, seed))
        print(f"  generated {count} {family} paths in {time.time() - t:.0f} s -> {file}", flush=True)
    return file


#: (label, spacing [rad] of the given waypoints (None: the dataset's own knots), knots kept)
RESPACINGS = (("as generated, knots kept", None, True), ("as generated", None, False),
              ("waypoints every 0.03 rad", 0.03, False), ("every third of those", 0.09, False),
              ("uniform every 0.15 rad", 0.15, False))


def respaced_files(out: Path, source, count: int) -> list[tuple[str, Path, bool]]:
    """User path files of the first ``count`` test paths of the policy's dataset: as generated
    (once with the knots kept, once re-knotted as every entrance does) and given again every
    0.03 / 0.09 / 0.15 rad of arc length (re-knotted)."""
    import numpy as np

    from mjx_pathtrack.core.spline_fit import fit_spline
    from mjx_pathtrack.paths import datasets

    cfg = source.config
    native = datasets.load_split(cfg.robot, cfg.dataset, "test", cfg.dataset_root)[:count]
    files = []
    for label, spacing, keep in RESPACINGS:
        file = out / "paths" / f"{cfg.robot}_{cfg.dataset}_{len(native)}_{'native' if spacing is None else spacing}.npz"
        if not file.is_file():
            given = native if spacing is None else [
                fit.point_at(np.append(np.arange(0.0, fit.length, spacing), fit.length))
                for fit in map(fit_spline, native)]
            datasets.save_split(file, given)
        files.append((f"one curve, any knots: {label}", file, keep))
    return files


def evaluate_row(source, label: str, paths, full: bool, args, robot, keep_knots: bool = False) -> dict:
    """One row: ``paths`` None = the policy's own test split; else a file given as user paths
    (re-knotted unless ``keep_knots``)."""
    from mjx_pathtrack.evaluation import jerk_optimum
    from mjx_pathtrack.evaluation import report as R

    user = None
    if paths is not None:
        user = R.load_user_paths(str(paths), source.config.robot, None if keep_knots else source.training_knot_rule())
    env, eval_robot, _ = R.build_env(source, user, "test", full)
    n = env.n_paths
    summary, table, _ = R.run_evaluation(env, source.policy, eval_robot, None, 0, min(n, 256), 0, True,
                                         args.jerk_optimum, Path(jerk_optimum.default_cache()), args.workers,
                                         measure=None if user is None else user.curves)
    term = summary["termination"]
    row = {"row": label, "episodes": summary["episodes"], "whole_paths": full,
           "end_reached": summary["end_reached_rate"], "ends_on_deviation": term.get("deviation", 0.0),
           "ratio_to_toppra": summary.get("ratio_to_toppra_mean"), "ratio_to_topp3": summary.get("ratio_to_topp3_mean"),
           "joint_dev_mean": summary.get("joint_dev_mean"), "joint_dev_max": summary.get("joint_dev_max"),
           "joint_dev_final": summary.get("joint_dev_final"), "cart_dev_mean_cm": summary.get("cart_pos_dev_cm_mean"),
           "limits_ok": bool(summary["limit_audit"]["ok"]), "task_failed": summary.get("task_failed_rate") if "task_failures" in summary else None}
    if user is not None:
        row["curve_distance_rad"] = max(p.joint_distance for p in user.prepared)
        cart = [p.cartesian_distance for p in user.prepared if p.cartesian_distance is not None]
        row["curve_distance_cm"] = 100 * max(cart) if cart else None
        row["limit_shift_rad"] = max(p.limit_shift for p in user.prepared)
    return row


def floors(row: dict, args, own_kind: bool) -> list[str]:
    missed = []
    if row.get("task_failed") is not None:   # the ball on the plate: falls, not end reached
        bar = args.max_falls_own if row["row"].startswith("own") else args.max_falls
        if row["task_failed"] > bar:
            missed.append(f"falls {100 * row['task_failed']:.1f} % > {100 * bar:.0f} %")
        if not row["limits_ok"]:
            missed.append("limit audit violated")
        return missed
    bar = args.min_end_own if own_kind else args.min_end
    if row["end_reached"] < bar:
        missed.append(f"end reached {100 * row['end_reached']:.1f} % < {100 * bar:.0f} %")
    ratio = row["ratio_to_toppra"]
    if ratio is not None and ratio == ratio and ratio > args.max_ratio:
        missed.append(f"x TOPP-RA {ratio:.3f} > {args.max_ratio}")
    if not row["limits_ok"]:
        missed.append("limit audit violated")
    return missed


def markdown(results: dict) -> str:
    f = lambda x, fmt: "–" if x is None or x != x else format(x, fmt)  # noqa: E731
    lines = []
    for source, rows in results.items():
        lines += [f"### {source}", "",
                  "| paths | episodes | end reached | ends on deviation | falls | × TOPP-RA | × TOPP3 "
                  "| joint dev. mean / max / final [rad] "
                  "| Cartesian mean [cm] | your curve vs policy's [rad / cm] | limits | floors |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            dist = "–" if "curve_distance_rad" not in r else \
                f"{r['curve_distance_rad']:.3f} / {f(r.get('curve_distance_cm'), '.2f')}"
            lines.append(
                f"| {r['row']} | {r['episodes']} | {100 * r['end_reached']:.1f} % | {100 * r['ends_on_deviation']:.1f} % "
                f"| {'–' if r.get('task_failed') is None else format(100 * r['task_failed'], '.1f') + ' %'} "
                f"| {f(r['ratio_to_toppra'], '.3f')} | {f(r['ratio_to_topp3'], '.3f')} "
                f"| {f(r['joint_dev_mean'], '.3f')} / {f(r['joint_dev_max'], '.3f')} / {f(r['joint_dev_final'], '.3f')} "
                f"| {f(r['cart_dev_mean_cm'], '.2f')} | {dist} | {'OK' if r['limits_ok'] else 'VIOLATED'} "
                f"| {'met' if not r['missed'] else '; '.join(r['missed'])} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    from mjx_pathtrack.evaluation import report as R
    from mjx_pathtrack.fileio import atomic_write_bytes
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.paths.families import BALL_FAMILIES, FAMILIES
    from mjx_pathtrack.robots import registry as robots

    out = Path(args.out)
    results, failed = {}, False
    for src in args.sources:
        source = R.load_policy_source(src, deterministic=not args.stochastic)
        if source.config.task == "ball_on_plate":
            source = dataclasses.replace(source, config=source.config.replace(ball_physics=args.ball_physics))
        if args.terminate_deviation is not None:
            source = dataclasses.replace(source, config=source.config.replace(terminate_deviation=args.terminate_deviation))
        cfg = source.config
        robot = robots.load_robot(cfg.robot, dt=cfg.env.dt)
        name = f"{src} ({'sampled' if args.stochastic else 'deterministic'})"
        print(f"{name}: robot {cfg.robot}, trained on {cfg.dataset}, knot rule {source.training_knot_rule()}", flush=True)
        plan = [(f"own test split ({cfg.dataset})", None, False, cfg.dataset in OWN_KINDS + ("mixed",), False)]
        if not args.no_respaced:
            plan += [(label, file, True, False, keep) for label, file, keep in respaced_files(out, source, args.count)]
        ball = cfg.task == "ball_on_plate"
        if not args.no_datasets and not ball:   # (the other datasets do not keep the plate level)
            for kind in datasets.known_kinds(cfg.robot):
                test = datasets.dataset_dir(cfg.robot, kind) / "test.npz"
                if kind != cfg.dataset and kind != "ball_balancing" and test.is_file():
                    plan.append((f"dataset {kind} (re-knotted, sub-paths)", test, False, kind in OWN_KINDS, False))
        for family in args.families or list(BALL_FAMILIES if ball else FAMILIES):
            if (family in BALL_FAMILIES) != ball:
                raise SystemExit(f"{src}: family {family} is for {'the ball on the plate' if not ball else 'path tracking'}"
                                 f", not this policy's task {cfg.task}")
            plan.append((f"{family} (whole paths)", family_file(out, robot, family, args.count, args.seed), True, False,
                         False))
        rows = []
        for label, paths, full, own_kind, keep in plan:
            t = time.time()
            row = evaluate_row(source, label, paths, full, args, robot, keep)
            row["missed"] = floors(row, args, own_kind)
            failed |= bool(row["missed"])
            rows.append(row)
            print(f"  {label:45s} end {100 * row['end_reached']:5.1f} %  dev-end {100 * row['ends_on_deviation']:5.1f} %  "
                  f"x{row['ratio_to_toppra'] or float('nan'):.3f}  dev {row['joint_dev_mean'] or float('nan'):.3f} rad  "
                  f"limits {'OK' if row['limits_ok'] else 'VIOLATED'}  ({time.time() - t:.0f} s)"
                  + (f"  MISSED: {'; '.join(row['missed'])}" if row["missed"] else ""), flush=True)
        # one curve, any knots: every re-knotted entry within 1 point of end reached and 3 % of the
        # ratio of the same curves given with their own knots (re-knotted, as every entrance does)
        native = next((r for r in rows if r["row"].endswith("as generated")), None)
        for r in rows:
            if native is None or not r["row"].startswith("one curve") or r is native or r["row"].endswith("kept"):
                continue
            if abs(r["end_reached"] - native["end_reached"]) > 0.01 + 1e-9:
                r["missed"].append(f"end reached {100 * r['end_reached']:.1f} % vs {100 * native['end_reached']:.1f} % "
                                   "as generated (> 1 point)")
            a, b = r["ratio_to_toppra"], native["ratio_to_toppra"]
            if a is not None and b is not None and a == a and b == b and abs(a / b - 1) > 0.03:
                r["missed"].append(f"x TOPP-RA {a:.3f} vs {b:.3f} as generated (> 3 %)")
            failed |= bool(r["missed"])
        results[name] = rows
    text = markdown(results)
    print("\n" + text)
    atomic_write_bytes(out / "generalisation.json", (json.dumps(results, indent=2) + "\n").encode())
    atomic_write_bytes(out / "generalisation.md", (text + "\n").encode())
    print(f"wrote {out / 'generalisation.json'}, {out / 'generalisation.md'}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
