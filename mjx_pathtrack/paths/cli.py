"""Command line of the path datasets: ``python -m mjx_pathtrack.paths {generate,stats,import}``.

    python -m mjx_pathtrack.paths generate --robot iiwa --kind random --num-train 200 --num-test 200
    python -m mjx_pathtrack.paths generate --kind ball_balancing --param workspace=whole --root /tmp/splines
    python -m mjx_pathtrack.paths stats [--robot iiwa] [--kind random] [--root splines]
    python -m mjx_pathtrack.paths import FILE --robot iiwa --kind my_paths [--split test]
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

from mjx_pathtrack.paths.datasets import (DEFAULT_ROOT, SPLITS, DatasetError, known_robots, load_split,
                                          split_stats, stats)
from mjx_pathtrack.paths.generate import generate_dataset
from mjx_pathtrack.paths.user_paths import import_paths


def _params(entries: list[str]) -> dict:
    """``--param NAME=VALUE`` entries as generator keyword arguments (VALUE as JSON, else text)."""
    params = {}
    for entry in entries:
        name, sep, value = entry.partition("=")
        if not sep or not name.strip():
            raise DatasetError(f"--param must be NAME=VALUE, got {entry!r}")
        try:
            params[name.strip()] = json.loads(value)
        except json.JSONDecodeError:
            params[name.strip()] = value
    return params


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mjx_pathtrack.paths",
                                     description="Reference-path datasets: generate, statistics and import.")
    sub = parser.add_subparsers(dest="command", required=True)
    p_stats = sub.add_parser("stats", help="knots per path, path length, knot spacing per split")
    p_stats.add_argument("--robot")
    p_stats.add_argument("--kind")
    p_stats.add_argument("--root", default=None, help=f"dataset root (default {DEFAULT_ROOT})")
    p_imp = sub.add_parser("import", help="validate user paths (.npz/.json/.csv) and store them")
    p_imp.add_argument("file")
    p_imp.add_argument("--robot", required=True, choices=known_robots())
    p_imp.add_argument("--kind", required=True, help="dataset name, e.g. my_paths")
    p_imp.add_argument("--split", default="test", choices=SPLITS)
    p_imp.add_argument("--root", default=None)
    p_imp.add_argument("--overwrite", action="store_true")
    p_imp.add_argument("--knot-rule-of", default="mixed", metavar="KIND",
                       help="re-knot the paths by the knot rule of this dataset of the robot (the training data of "
                            "the policy that will track them; default mixed, the iiwa's; another robot's default "
                            "is random)")
    p_imp.add_argument("--keep-knots", action="store_true", help="store the knots as given (no re-knotting)")
    p_imp.add_argument("--cartesian", action="store_true",
                       help="the file holds tool positions x, y, z [m] per waypoint (the robot's target point), "
                            "turned into joint paths by IK with continuity, limit and self-collision checks")
    p_imp.add_argument("--start", default=None, metavar="Q1,Q2,...",
                       help="with --cartesian: the joint configuration [rad] the IK starts from (default: the "
                            "collision-free solution of the first waypoint nearest the middle of the joint ranges)")
    p_gen = sub.add_parser("generate", help="generate a dataset (kinds: see generate.KINDS, e.g. random, target_point)")
    p_gen.add_argument("--robot", default="iiwa", choices=known_robots())
    p_gen.add_argument("--kind", default="random")
    p_gen.add_argument("--num-train", type=int, default=200)
    p_gen.add_argument("--num-test", type=int, default=200)
    p_gen.add_argument("--seed", type=int, default=0)
    p_gen.add_argument("--root", default=None)
    p_gen.add_argument("--overwrite", action="store_true")
    p_gen.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                       help="a parameter of the kind's generator (VALUE read as JSON, else as text), e.g. "
                            "--param persistent_share=0.333 (mixed), --param workspace=whole (ball_balancing)")
    args = parser.parse_args(argv)
    try:
        if args.command == "generate":
            directory = generate_dataset(args.robot, args.kind, args.num_train, args.num_test, args.seed,
                                         args.root, args.overwrite, **_params(args.param))
            for name, st in stats(args.robot, args.kind, args.root).items():
                print(st.line(name))
            print(f"written to {directory}")
        elif args.command == "stats":
            table = stats(args.robot, args.kind, args.root)
            if not table:
                print(f"no datasets under {args.root or DEFAULT_ROOT}")
            for name, st in table.items():
                print(st.line(name))
        else:
            from mjx_pathtrack.core.knot_rule import KnotRule
            from mjx_pathtrack.paths.datasets import known_kinds, read_config
            from mjx_pathtrack.robots.registry import POS_BUFFER

            rule = None
            if not args.keep_knots:
                rule_kind = args.knot_rule_of
                if rule_kind == "mixed" and "mixed" not in known_kinds(args.robot):
                    rule_kind = "random"
                rule = KnotRule.of_dataset(read_config(args.robot, rule_kind))
            if args.start is not None and not args.cartesian:
                raise DatasetError("--start applies to --cartesian only")
            try:
                q_start = None if args.start is None else [float(x) for x in args.start.split(",")]
            except ValueError:
                raise DatasetError(f"--start must be comma-separated joint positions in rad, got {args.start!r}") from None
            directory = import_paths(args.file, args.robot, args.kind, args.split, args.root,
                                     overwrite=args.overwrite, rule=rule, allowance=POS_BUFFER,
                                     cartesian=args.cartesian, q_start=q_start)
            source = read_config(args.robot, args.kind, args.root)["source"][args.split]
            if "cartesian" in source:
                print("\n".join(source["cartesian"]["report"]))
            print(f"imported into {directory}" + ("" if rule is None else
                  f" (re-knotted by the rule of {args.robot}/{rule_kind}: largest distance from your curve "
                  f"{source['curve_distance_rad_max']:.4f} rad)")
                  + (f"; knots moved into the limits by up to {source['limit_shift_rad_max']:.4f} rad"
                     if source["limit_shift_rad_max"] > 0 else ""))
            print(split_stats(load_split(args.robot, args.kind, args.split, args.root))
                  .line(f"{args.robot}/{args.kind}/{args.split}"))
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0

