"""Evaluate a trained path-tracking policy: the paper 000 §IV tables (I, VI, IX) and a limit audit.

    python evaluate.py runs/iiwa_random                 # run dir: config.json + params.msgpack
    python evaluate.py runs/iiwa_random/export          # exported policy (manifest.json)
    python evaluate.py RUN --checkpoint latest          # a run still training: its newest checkpoint
    python evaluate.py RUN --paths my_paths.csv         # user paths (datasets import format)
    python evaluate.py RUN --episodes 50 --seed 1 --full-paths --out eval/
    python evaluate.py runs/armar4_target_point --floating-base --terminate-deviation inf  # ARMAR-4 on the floor: falls
    python evaluate.py policies/iiwa --full-paths --video                 # + RUN/eval/episode0.mp4 (offscreen)
    python evaluate.py policies/iiwa --video run.gif --video-episodes 0 3 # run_episode0.gif, run_episode3.gif

Writes metrics.json, episodes.csv and PNG plots of one episode to --out (default RUN/eval, with
--checkpoint RUN/eval_latest or RUN/eval_STEP).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import mjx_pathtrack
from mjx_pathtrack.config.stored import ALLOW_PICKLE_HELP  # (NumPy only)

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", metavar="RUN_DIR_OR_EXPORT")
    parser.add_argument("--allow-pickle", action="store_true", help=ALLOW_PICKLE_HELP)
    parser.add_argument("--checkpoint", default=None, metavar="latest|STEP",
                        help="a run directory's checkpoint (a run still training or cut off) instead of its final "
                             "params.msgpack; default output SOURCE/eval_STEP")
    parser.add_argument("--paths", default=None,
                        help="user path file (.npz/.json/.csv) instead of the dataset split; each path is re-knotted "
                             "by the policy's knot rule (its training data's), knots up to the URDF limits are moved "
                             "onto the model's, and deviations are measured against your curve")
    parser.add_argument("--keep-knots", action="store_true",
                        help="with --paths: give the policy the knots as they are in the file (no re-knotting)")
    parser.add_argument("--split", default="test", choices=("train", "test"))
    parser.add_argument("--episodes", type=int, default=None, help="default: one per path")
    parser.add_argument("--seed", type=int, default=0, help="sub-path draw")
    parser.add_argument("--full-paths", action="store_true", help="whole paths instead of random sub-paths")
    parser.add_argument("--batch", type=int, default=256,
                        help="episodes per jitted batch (the sub-paths drawn depend on --seed and --batch)")
    parser.add_argument("--plot-episode", type=int, default=0)
    parser.add_argument("--timing-decisions", type=int, default=200, help="0: skip the computation-time measurement")
    parser.add_argument("--stochastic", action="store_true",
                        help="sample actions from the trained Gaussian (as in training and the authors' evaluate.py "
                             "without --no_exploration) instead of taking its mean; run directories only")
    parser.add_argument("--terminate-deviation", type=float, default=None, metavar="RAD",
                        help="end episodes at this weighted deviation instead of the training config's "
                             "(inf: never, e.g. to see whether a task failure follows a deviation)")
    parser.add_argument("--end-tolerance", type=float, default=None, metavar="RAD",
                        help="count the path end as reached (and brake) this arc length before it, instead of the "
                             "training config's (0: the papers' rule); a deterministic policy can stall just short "
                             "of the end")
    parser.add_argument("--end-braking", choices=("at_end", "predictive"), default=None,
                        help="when braking at the path end starts, instead of the training config's: at_end (the "
                             "papers: once the end is reached) or predictive (once the fastest stop would reach it)")
    parser.add_argument("--end-stop", choices=("fastest", "end_knot"), default=None,
                        help="how the robot stops at the path end, instead of the training config's: fastest (the "
                             "papers: every joint brakes on its own) or end_knot (every path joint comes to rest at "
                             "the end knot)")
    parser.add_argument("--end-knot-tolerance", type=float, default=None, metavar="RAD",
                        help="with --end-stop end_knot: a joint brakes once its stop ends this close to its end-knot "
                             "coordinate (smaller: closer to the end knot, slower), instead of the training config's")
    parser.add_argument("--ball-physics", choices=("arm", "plate", "rolling"), default=None,
                        help="ball_on_plate: evaluate in the full-arm scene (arm) or with the plate's motion "
                             "prescribed (plate); default: the scene the run trained in")
    parser.add_argument("--floating-base", action="store_true",
                        help="a plain ARMAR-4 tracking run (robot armar4) standing on the floor, legs fixed (welded, "
                             "MJX physics at 80 Hz, no pelvis observation): the papers' Table VIII 'no balancing "
                             "reward' row; reports how often the robot fell")
    parser.add_argument("--no-toppra", action="store_true", help="skip the TOPP-RA baseline")
    parser.add_argument("--jerk-optimum", action="store_true",
                        help="also the jerk-limited time-optimal duration of every episode (TOPP3 of copp-py, ~1 s "
                             "per 7-joint path, solved on --workers processes, kept in --topp3-cache)")
    parser.add_argument("--topp3-cache", default=None, metavar="FILE",
                        help="JSON cache of TOPP3 durations (default ~/.cache/mjx_pathtrack/topp3.json; 'none': off)")
    parser.add_argument("--workers", type=int, default=2, help="processes for the TOPP3 baseline")
    parser.add_argument("--online-baselines", action="store_true",
                        help="also run the online peers (Ruckig towards a look-ahead point, every 1/240 s) on the "
                             "same episodes of the first batch, knowing what the policy knows (state + next N "
                             "knots); path tracking only (mjx_pathtrack.evaluation.online_peers)")
    parser.add_argument("--out", default=None, help="output directory (default SOURCE/eval)")
    parser.add_argument("--video", nargs="?", const="", default=None, metavar="FILE",
                        help="also render episodes offscreen (MuJoCo renderer, MUJOCO_GL=egl unless set): the robot, "
                             "the reference tool path, the executed trace, the ball; FILE .mp4 / .gif / .png (last "
                             "frame); default OUT/episodeB.mp4")
    parser.add_argument("--video-episodes", type=int, nargs="+", default=None, metavar="B",
                        help="episodes to render (of the first batch; default --plot-episode)")
    parser.add_argument("--video-size", default="640x480", metavar="WxH", help="frame size in pixels")
    parser.add_argument("--video-fps", type=int, default=30, help="frames per second of motion")
    return parser.parse_args(argv)


def video_size(text: str) -> tuple[int, int] | None:
    """``"WxH"`` -> (W, H), or None if malformed."""
    parts = text.lower().split("x")
    return (int(parts[0]), int(parts[1])) if len(parts) == 2 and all(p.isdigit() for p in parts) else None


def option_problem(args) -> str | None:
    """The first problem of the command line's options that needs no policy, dataset or JAX
    (one line, as ``train.py``'s option errors), or None."""
    from pathlib import Path

    inf = float("inf")
    checks = (
        (not Path(args.source).is_dir(), f"no run or export directory at {args.source}"),
        (args.paths and not Path(args.paths).is_file(), f"--paths {args.paths}: no such file"),
        (args.keep_knots and not args.paths, "--keep-knots applies to --paths only"),
        (args.episodes is not None and args.episodes < 1, f"--episodes must be >= 1, got {args.episodes}"),
        (args.batch < 1, f"--batch must be >= 1, got {args.batch}"),
        (args.plot_episode < 0, f"--plot-episode must be >= 0, got {args.plot_episode}"),
        (args.timing_decisions < 0, f"--timing-decisions must be >= 0, got {args.timing_decisions}"),
        (args.workers < 1, f"--workers must be >= 1, got {args.workers}"),
        (args.terminate_deviation is not None and not args.terminate_deviation > 0,   # inf: no deviation limit
         f"--terminate-deviation must be a number > 0 (inf: no limit), got {args.terminate_deviation}"),
        (args.end_knot_tolerance is not None and not 0 < args.end_knot_tolerance < inf,
         f"--end-knot-tolerance must be a finite number > 0, got {args.end_knot_tolerance}"),
        (args.end_tolerance is not None and not 0 <= args.end_tolerance < inf,
         f"--end-tolerance must be a finite number >= 0, got {args.end_tolerance}"),
        (args.checkpoint is not None and args.checkpoint != "latest" and not args.checkpoint.isdigit(),
         f"--checkpoint must be 'latest' or a step (a whole number), got {args.checkpoint!r}"),
        (bool(args.video) and Path(args.video or "x.mp4").suffix.lower() not in (".mp4", ".gif", ".png"),
         f"--video {args.video}: the file name must end in .mp4, .gif or .png"),
        (args.video is None and (args.video_episodes is not None), "--video-episodes applies to --video only"),
        (args.video_episodes is not None and min(args.video_episodes) < 0,
         f"--video-episodes must be >= 0, got {args.video_episodes}"),
        (args.video_episodes is not None and max(args.video_episodes) >= min(args.batch, args.episodes or args.batch),
         f"--video-episodes {args.video_episodes}: only episodes of the first batch can be rendered "
         f"(0..{min(args.batch, args.episodes or args.batch) - 1})"),
        (video_size(args.video_size) is None or not all(16 <= x <= 4096 for x in video_size(args.video_size)),
         f"--video-size must be WxH with 16..4096 pixels per side, got {args.video_size!r}"),
        (not 1 <= args.video_fps <= 240, f"--video-fps must be 1..240, got {args.video_fps}"),
    )
    return next((message for failed, message in checks if failed), None)


def online_peer_lines(env, first, table: dict, robot, measure) -> list[dict]:
    """Print the policy and the online peers on the episodes of the first batch; returns their rows
    (:func:`mjx_pathtrack.evaluation.online_peers.summary_row`)."""
    from mjx_pathtrack.evaluation import online_peers as P

    n = len(first.s_start)
    rows = [P.summary_row("policy", {k: v[:n] for k, v in table.items()})]
    for peer in (P.RuckigLookahead(),):
        rows.append(P.summary_row(f"{peer.name} ({peer.lookahead:g} rad, {peer.speed_factor:g})",
                                  *P.peer_table(env, peer, first, robot, measure)))
    print(f"\nOnline peers on the same {n} episodes (state + next {env.config.n_next} knots; "
          "mjx_pathtrack.evaluation.online_peers)")
    for row in rows:
        contour = "" if row["contour_cm"] is None else f"   contour {row['contour_cm']:.2f} cm"
        cost = "" if row["compute_mean_ms"] != row["compute_mean_ms"] else \
            f"   {row['compute_mean_ms']:.2f} ms per decision"
        print(f"  {row['controller']:<40} end {100 * row['end_reached']:5.1f} %   stop {row['stop_time_s']:6.3f} s   "
              f"x TOPP-RA {row['ratio_to_toppra']:.3f}   joint dev {row['joint_dev_mean']:.3f} rad{contour}   "
              f"limits {'OK' if row['audit_ok'] else 'VIOLATED'}{cost}")
    return rows


def main(argv=None) -> int:
    args = parse_args(argv)
    from pathlib import Path

    # the option checks first: the imports below (JAX, Brax, MuJoCo) and the policy take seconds
    problem = option_problem(args)
    if problem:
        print(f"evaluate.py: error: {problem}", file=sys.stderr)
        return 2
    if args.video is not None:
        import os

        os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen OpenGL; read when mujoco is first imported
    from mjx_pathtrack.evaluation import report as R
    from mjx_pathtrack.paths.datasets import DatasetError

    try:
        source = R.load_policy_source(args.source, deterministic=not args.stochastic, checkpoint=args.checkpoint,
                                      allow_pickle=args.allow_pickle)
        # the training config's settings that the flags above replace (unset flags keep them)
        overrides = {name: getattr(args, name) for name in ("terminate_deviation", "end_braking", "end_stop",
                                                            "end_knot_tolerance", "end_tolerance", "ball_physics")}
        overrides = {name: value for name, value in overrides.items() if value is not None}
        source = dataclasses.replace(source, config=source.config.replace(**overrides))
        if args.online_baselines and (source.config.task != "tracking" or args.floating_base):
            raise R.EvaluationError(f"--online-baselines compares path-tracking policies, not task "
                                    f"{source.config.task}{' on a floating base' if args.floating_base else ''}")
        user = None
        if args.paths:
            user = R.load_user_paths(args.paths, source.config.robot,
                                     None if args.keep_knots else source.training_knot_rule())
        env, robot, label = R.build_env(source, user, args.split, args.full_paths, args.floating_base)
    except (R.EvaluationError, DatasetError) as e:
        print(f"evaluate.py: error: {e}", file=sys.stderr)
        return 2
    from mjx_pathtrack.evaluation import jerk_optimum

    cache = None if args.topp3_cache == "none" else Path(args.topp3_cache or jerk_optimum.default_cache())
    if user is not None:
        print("\n".join(user.report_lines()) + "\n")
    summary, table, first = R.run_evaluation(env, source.policy, robot, args.episodes, args.seed, args.batch,
                                             args.timing_decisions, not args.no_toppra, args.jerk_optimum, cache,
                                             max(args.workers, 1), measure=None if user is None else user.curves)
    if user is not None:
        summary["user_paths"] = {"knot_rule": None if user.rule is None else user.rule.to_json(),
                                 "paths": [p.summary() for p in user.prepared]}
    episode = min(max(args.plot_episode, 0), len(first.s_start) - 1)
    ball_task = source.config.task == "ball_on_plate"
    whole = args.full_paths or ball_task  # the ball task always runs whole paths
    meta = {"source": str(source.path), "source_kind": source.kind, "checkpoint": args.checkpoint, "robot": source.config.robot, "paths": label,
            "seed": args.seed, "full_paths": whole,
            "actions": "sampled" if args.stochastic else "deterministic",
            "terminate_deviation": source.config.env.terminate_deviation, "end_tolerance": source.config.env.end_tolerance,
            "end_braking": source.config.env.end_braking, "end_stop": source.config.env.end_stop,
            "end_knot_tolerance": source.config.env.end_knot_tolerance, "ball_physics": source.config.ball_on_plate.physics,
            "floating_base": args.floating_base, "plot_episode": episode}
    physics = f", {source.config.ball_on_plate.physics} ball" if ball_task else ""
    physics += f", on the floor, legs fixed, {env.robot.n_substeps / env.robot.dt:.0f} Hz physics" if args.floating_base else ""
    title = (f"{source.kind} {source.path} on {label} ({'full paths' if whole else f'sub-paths, seed {args.seed}'}"
             f"{physics}{', sampled actions' if args.stochastic else ''})")
    print(R.format_report(summary, title, source.config.robot))
    if args.online_baselines:
        summary["online_peers"] = online_peer_lines(env, first, table, robot, None if user is None else user.curves)
    default = "eval" if args.checkpoint is None else f"eval_{args.checkpoint}"
    out = Path(args.out) if args.out else Path(args.source) / default
    files = R.write_outputs(out, summary, table, meta, env, first, robot, episode)
    if args.video is not None:
        from mjx_pathtrack.evaluation import video

        width, height = video_size(args.video_size)
        settings = video.VideoSettings(width=width, height=height, fps=args.video_fps)
        chosen = args.video_episodes or [episode]
        if max(chosen) >= len(first.s_start):
            print(f"evaluate.py: error: --video-episodes {max(chosen)}: the first batch has {len(first.s_start)} "
                  "episodes", file=sys.stderr)
            return 2
        for b in chosen:
            if not args.video:
                file = out / f"episode{b}.mp4"
            elif len(chosen) == 1:
                file = Path(args.video)
            else:
                file = Path(args.video).with_name(f"{Path(args.video).stem}_episode{b}{Path(args.video).suffix}")
            label_b = f"{Path(args.source).name}: {label}, episode {b}"
            try:
                files.append(video.write_episode_video(file, env, first, robot, b, settings,
                                                       None if user is None else user.curves, label_b))
            except video.RenderError as e:
                print(f"evaluate.py: error: {e}", file=sys.stderr)
                return 2
    print("\nwrote " + ", ".join(str(f) for f in files))
    return 0 if summary["limit_audit"]["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
