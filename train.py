"""Train a path-tracking policy with Brax PPO on batched environments.

    python train.py                      # iiwa, mixed paths, CPU-sized default run (~8 min on 2 cores)
    python train.py --preset paper       # the same recipe at 40 M steps, iiwa: alpha 2 (~30 min on 2 cores)
    python train.py --help               # all flags
    python train.py --out runs/x --resume  # continue after a kill from the last checkpoint
    python train.py --init-from runs/x --alpha 2.5 --init-noise-std 0.05 --out runs/y  # fine-tune x's policy
    python train.py --task ball_on_plate [--no-ball-reward]   # iiwa ball on plate (MJX), with / without R_ball
    python train.py --sweep sweep.yaml [--out DIR]  # a grid of runs + summary.csv (mjx_pathtrack.sweeps.run)
    python train.py --robot armar6         # ARMAR-6 with the papers' settings (alpha 1, 20 s, no R_action)
    python train.py --task balance --legs fixed|controlled   # ARMAR-4 keeping its balance (MJX physics)

A robot or task with a preset (mjx_pathtrack.config.presets) sets the papers' values as the defaults
of the other flags; flags given explicitly still win. Every flag is an option of
mjx_pathtrack.config.run.TrainConfig by its flat name (--alpha is env.reward.distance).

Multi-host: start the same command on every host with --distributed --coordinator host0:1234
--num-processes N --process-id i (or under SLURM / Open MPI, which JAX detects); Brax PPO then
shards the environments over all devices of all processes.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import mjx_pathtrack
from mjx_pathtrack.config.stored import ALLOW_PICKLE_HELP  # (NumPy only)


def parse_args(argv=None):
    """``(args, TrainConfig)`` of the command line: one flag per flat option of
    :class:`~mjx_pathtrack.config.run.TrainConfig` (``--alpha``, ``--num-envs``, ...), whose defaults a
    robot's or task's preset and then ``--preset`` replace (:mod:`mjx_pathtrack.config.presets`)."""
    from mjx_pathtrack.config.options import add_flags, from_flags
    from mjx_pathtrack.config.presets import RECIPES, preset, recipe
    from mjx_pathtrack.config.run import CHOICES, TrainConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default=None, choices=sorted(RECIPES),
                        help="a training recipe's settings as the defaults of the other flags "
                             "(mjx_pathtrack.config.presets.RECIPES; paper: the default recipe at 40 M steps, for the iiwa with alpha 2, "
                             "~30 min on 2 CPU cores)")
    parser.add_argument("--no-ball-reward", action="store_true",
                        help="ball_on_plate: train without R_ball (and without the ball sensor), i.e. --ball-reward 0")
    parser.add_argument("--out", default=None,
                        help="run directory (config, logs, checkpoints; default runs/<robot>_<dataset>, "
                             "runs/ball_on_plate or runs/balance_<legs>), or with --sweep the sweep's output directory")
    parser.add_argument("--sweep", default=None, metavar="FILE",
                        help="run the grid of a sweep file (YAML, see mjx_pathtrack/sweeps/run.py); the training "
                             "flags below are then ignored: put them in the file's 'base'")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out exactly from its last checkpoint (same config)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the run that --out holds (without it, a directory holding a run is refused)")
    parser.add_argument("--allow-pickle", action="store_true",
                        help="--resume / --init-from: " + ALLOW_PICKLE_HELP)
    parser.add_argument("--compilation-cache", default=None, metavar="DIR",
                        help="keep JAX's persistent compilation cache in DIR (default: none, unless "
                             "JAX_COMPILATION_CACHE_DIR is set): a repeated run skips most compilation, and Brax's "
                             "training epoch, compiled twice in every run, loads the second time")
    parser.add_argument("--distributed", action="store_true",
                        help="multi-host: call jax.distributed.initialize() first (cluster auto-detection "
                             "or the three flags below)")
    parser.add_argument("--coordinator", default=None, help="host:port of process 0 (or JAX_COORDINATOR_ADDRESS)")
    parser.add_argument("--num-processes", type=int, default=None)
    parser.add_argument("--process-id", type=int, default=None)
    add_flags(parser, TrainConfig, CHOICES)
    known, _ = parser.parse_known_args(argv)
    try:
        parser.set_defaults(**preset(known.robot, known.task, known.legs))
    except ValueError as e:
        parser.error(str(e))
    # the robot and dataset the robot/task presets and the explicit flags give
    chosen, _ = parser.parse_known_args(argv)
    parser.set_defaults(**recipe(known.preset, chosen.robot, chosen.dataset))
    args = parser.parse_args(argv)
    if args.no_ball_reward:
        args.ball_reward = 0.0
    if args.out is None and not args.sweep:  # (a sweep has its own default output directory)
        args.out = {"balance": f"runs/balance_{args.legs}", "ball_on_plate": "runs/ball_on_plate"}.get(
            args.task, f"runs/{args.robot}_{args.dataset}")
        args.out += f"_{args.preset}" if args.preset else ""
    return args, from_flags(args, TrainConfig)


def use_compilation_cache(directory: str | None) -> None:
    """Point JAX's persistent compilation cache at ``directory`` (``--compilation-cache``; None:
    leave JAX's setting, e.g. a set ``JAX_COMPILATION_CACHE_DIR``). Exits with a clear message if
    the directory cannot be created."""
    if directory is None:
        return
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as e:
        raise SystemExit(f"--compilation-cache {directory}: cannot create the directory ({e})") from e
    import jax

    jax.config.update("jax_compilation_cache_dir", directory)


def main(argv=None) -> int:
    from mjx_pathtrack.config.options import ConfigError

    try:
        args, config = parse_args(argv)  # (imports jax, but its backend starts later)
    except ConfigError as e:
        print(f"train.py: error: {e}", file=sys.stderr)
        return 2
    # the CPU flag batched MJX needs; without MJX physics XLA's default CPU fusion emitters train
    # faster (mjx_pathtrack/_xla.py); a user's own flag is kept
    if args.sweep:
        from mjx_pathtrack.sweeps.spec import steps_mjx_physics

        mjx_physics = steps_mjx_physics(args.sweep)
    else:
        mjx_physics = config.executor != "kinematic"
    mjx_pathtrack.prepare_xla(mjx_physics=mjx_physics)
    use_compilation_cache(args.compilation_cache)
    if args.sweep:
        from mjx_pathtrack.sweeps import run as sweep

        return sweep.main([args.sweep] + (["--out", args.out] if args.out else []))
    import jax

    if args.distributed:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    from mjx_pathtrack.paths.datasets import DatasetError
    from mjx_pathtrack.config.run_dir import RunDirError
    from mjx_pathtrack.config.run import ConfigError
    from mjx_pathtrack.rl.training import TrainingDiverged, train

    print(f"devices: {jax.devices()}", flush=True)
    try:
        train(config, args.out, resume=args.resume, overwrite=args.overwrite, allow_pickle=args.allow_pickle)
    except (ConfigError, RunDirError, DatasetError) as e:
        print(f"train.py: error: {e}", file=sys.stderr)
        return 2
    except TrainingDiverged as e:
        print(f"train.py: {e}", file=sys.stderr)
        return 1
    print(run_summary(Path(args.out)), flush=True)
    return 0


def run_summary(run: Path) -> str:
    """What a finished run directory holds, and the commands that use it."""
    def held(names):
        return ", ".join(n + ("/" if (run / n).is_dir() else "") for n in names if (run / n).exists())

    lines = [f"\nrun directory {run}: {held(['config.json', 'progress.csv', 'tensorboard', 'checkpoints', 'params.msgpack', 'report.json', 'export'])}",
             f"  export/: {held(['export/manifest.json', 'export/policy.jaxexport', 'export/policy.onnx']).replace('export/', '')}",
             f"  python evaluate.py {run}/export                      # the deployed policy on the test paths",
             f"  python evaluate.py {run} --stochastic                # the sampled policy beside it",
             f"  python benchmarks/generalisation.py {run}/export     # on path families it never saw",
             f"  python evaluate.py {run}/export --full-paths --episodes 1 --video  # watch it: {run}/export/eval/episode0.mp4",
             f"  tensorboard --logdir {run}/tensorboard"]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
