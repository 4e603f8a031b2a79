"""The deployed policy beside the online peers a user would run instead, on the same paths.

    python benchmarks/online_peers.py policies/iiwa                      # own test curves + families
    python benchmarks/online_peers.py policies/iiwa --count 20 --families planner_dense
    python benchmarks/online_peers.py policies/iiwa --tune                # pick the peer's settings on train paths

Every controller knows the same: its kinematic state and the next ``N`` knots of the policy's
(re-knotted) reference, nothing beyond (:mod:`mjx_pathtrack.evaluation.online_peers`). Rows:
whole paths of the policy's own test split (the first ``--count``) and of the generalisation
families (:mod:`mjx_pathtrack.paths.families`, given as user paths, re-knotted by the policy's
rule, deviations against the user's curve, as ``benchmarks/generalisation.py``). Per controller:
end reached, stop time over TOPP-RA's (offline, the whole path known), joint deviation at equal
arc length (mean / max / final), Cartesian contour deviation (the tool's distance from the
reference's tool curve), the limit audit (largest ratio to a limit at any instant) and the compute
per decision step (mean / max; the policy: one jitted decision, ``evaluate.py``'s Table IX; a
peer: its library's calls of that step, 24 Ruckig cycles).

``--tune`` runs the Ruckig look-ahead over a grid of its two settings (look-ahead distance, share
of the speed cap) on whole paths of the policy's *training* split and prints, for each, end
reached, stop time and deviations: choose the settings there, never on the test paths.
Writes ``online_peers.json`` and ``online_peers.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import mjx_pathtrack

mjx_pathtrack.prepare_xla()

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generalisation  # noqa: E402  (family files, shared with the generalisation benchmark)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", metavar="RUN_OR_EXPORT")
    p.add_argument("--count", type=int, default=50, help="whole paths per row")
    p.add_argument("--families", nargs="*", default=None,
                   help="generalisation families (default: all of mjx_pathtrack.paths.families; none: no family rows)")
    p.add_argument("--seed", type=int, default=12345, help="family generation seed")
    p.add_argument("--lookahead", type=float, default=None, help="Ruckig look-ahead [rad of arc] (default: the peer's)")
    p.add_argument("--speed-factor", type=float, default=None, help="Ruckig target speed share (default: the peer's)")
    p.add_argument("--tune", action="store_true", help="grid of the Ruckig settings on training paths instead")
    p.add_argument("--out", default="benchmarks/results/online_peers")
    args = p.parse_args(argv)
    if args.count < 1:
        p.error(f"--count must be >= 1, got {args.count}")
    return args


def compare(env, source, robot, peers, measure=None, timing: bool = True) -> list[dict]:
    """The policy and each peer on every episode of ``env`` (whole paths, one batch)."""
    from mjx_pathtrack.evaluation import online_peers as P
    from mjx_pathtrack.evaluation import report as R

    n = env.n_paths
    summary, table, first = R.run_evaluation(env, source.policy, robot, None, 0, n, 200 if timing else 0, True,
                                             measure=measure)
    policy_compute = [summary["computation_time"]["mean_s"], summary["computation_time"]["max_s"]] if timing else None
    rows = [P.summary_row("policy (deterministic export)", table, policy_compute)]
    for peer in peers:
        t = time.time()
        peer_table, compute = P.peer_table(env, peer, first, robot, measure)
        rows.append(P.summary_row(f"{peer.name} ({peer.lookahead:g} rad, {peer.speed_factor:g})", peer_table, compute))
        print(f"    {peer.name}: {n} episodes in {time.time() - t:.0f} s", flush=True)
    return rows


def markdown(results: list[dict]) -> str:
    f = lambda x, fmt: "–" if x is None or x != x else format(x, fmt)  # noqa: E731
    lines = ["| paths | controller | episodes | end reached | × TOPP-RA | joint dev. mean / max / final [rad] "
             "| contour [cm] | limit audit (max ratio) | compute per decision mean / max [ms] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for block in results:
        for r in block["controllers"]:
            lines.append(f"| {block['row']} | {r['controller']} | {r['episodes']} | {100 * r['end_reached']:.1f} % | "
                         f"{f(r['ratio_to_toppra'], '.3f')} | {r['joint_dev_mean']:.3f} / {r['joint_dev_max']:.3f} / "
                         f"{r['joint_dev_final']:.3f} | {r['contour_cm']:.2f} | "
                         f"{'OK' if r['audit_ok'] else 'VIOLATED'} ({r['audit_worst']} "
                         f"{r['audit'][r['audit_worst']]:.4f}) | "
                         f"{f(r['compute_mean_ms'], '.3f')} / {f(r['compute_max_ms'], '.3f')} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)
    from mjx_pathtrack.evaluation import online_peers as P
    from mjx_pathtrack.evaluation import report as R
    from mjx_pathtrack.fileio import atomic_write_bytes
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.paths.families import FAMILIES
    from mjx_pathtrack.robots import registry as robots

    source = R.load_policy_source(args.source)
    cfg = source.config
    if cfg.task not in ("tracking",):
        raise SystemExit(f"{args.source}: online peers compare path-tracking policies, not task {cfg.task!r}")
    robot = robots.load_robot(cfg.robot, dt=cfg.env.dt)
    out = Path(args.out)
    settings = {k: v for k, v in (("lookahead", args.lookahead), ("speed_factor", args.speed_factor)) if v is not None}
    if args.tune:
        native = datasets.load_split(cfg.robot, cfg.dataset, "train", cfg.dataset_root)[:args.count]
        file = out / "paths" / f"{cfg.robot}_{cfg.dataset}_train_{args.count}.npz"
        datasets.save_split(file, native)
        user = R.load_user_paths(str(file), cfg.robot, None)   # the training knots as they are
        env, eval_robot, _ = R.build_env(source, user, "test", True)
        peers = [P.RuckigLookahead(lookahead=la, speed_factor=sf)
                 for la, sf in itertools.product((0.1, 0.2, 0.3, 0.5), (0.3, 0.5, 0.7, 1.0))]
        results = [{"row": f"training split ({cfg.dataset}), {env.n_paths} whole paths",
                    "controllers": compare(env, source, eval_robot, peers, timing=False)}]
    else:
        peers = [P.RuckigLookahead(**settings)]
        plan = [(f"own test split ({cfg.dataset}), whole paths", None)]
        native = datasets.load_split(cfg.robot, cfg.dataset, "test", cfg.dataset_root)[:args.count]
        own = out / "paths" / f"{cfg.robot}_{cfg.dataset}_test_{args.count}.npz"
        datasets.save_split(own, native)
        plan[0] = (plan[0][0], own)
        families = list(FAMILIES) if args.families is None else args.families
        unknown = sorted(set(families) - set(FAMILIES))
        if unknown:
            raise SystemExit(f"unknown families {unknown}; known: {', '.join(FAMILIES)}")
        plan += [(f"{family} (whole paths)", generalisation.family_file(out, robot, family, args.count, args.seed))
                 for family in families]
        results = []
        for label, file in plan:
            print(f"  {label}", flush=True)
            keep = file == own
            user = R.load_user_paths(str(file), cfg.robot, None if keep else source.training_knot_rule())
            env, eval_robot, _ = R.build_env(source, user, "test", True)
            results.append({"row": label, "controllers": compare(env, source, eval_robot, peers,
                                                                 measure=None if keep else user.curves)})
    text = markdown(results)
    print("\n" + text)
    atomic_write_bytes(out / "online_peers.json", (json.dumps({"source": args.source, "tune": args.tune,
                                                                "results": results}, indent=2) + "\n").encode())
    atomic_write_bytes(out / "online_peers.md", text.encode())
    print(f"wrote {out / 'online_peers.md'}, {out / 'online_peers.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
