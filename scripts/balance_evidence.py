"""Does the balance reward make ARMAR-4 fall less often? Same budget, with and without it.

    python scripts/balance_evidence.py [--root /tmp/balance_splines] [--out runs/balance_evidence]
        [--legs controlled] [--num-timesteps 30000] [--num-envs 64] [--batch-size B]
        [--scales 1.0 0.0] [--uncensored] [train.py options ...]

1. generates a small ARMAR-4 upper-body random dataset under ``--root`` if it is missing
   (random safe motions as ``datasets generate``, resampled by curvature, but WITHOUT the
   self-collision check, which takes too long on a shared 2-core CPU; the MJX balance model has no
   self-collision contacts anyway);
2. trains ``train.py --task balance`` twice with the same seed and budget, ``--balance-reward 1``
   and ``--balance-reward 0``;
3. prints the share of test episodes in which the robot fell (``task_failed``), before and after
   training, from each run's ``report.json``;
4. with ``--uncensored``, also evaluates each trained policy with ``evaluate.py
   --terminate-deviation inf``: episodes then run on past the 0.25 rad deviation limit, which
   otherwise ends weak policies' episodes before they could fall, and prints that fall rate.

Options this script does not know go to ``train.py`` unchanged, after its own, so they can
override them (e.g. ``--num-evals 9 --compilation-cache /tmp/jax_cache``).

A run whose ``report.json`` exists is not trained again (``--scales 1.0`` and ``--scales 0.0``
can run as separate calls, e.g. on a lent GPU with a per-call time limit).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def make_dataset(root: Path, n_train: int, n_test: int) -> None:
    sys.path.insert(0, str(REPO))
    import mjx_pathtrack
    mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
    import numpy as np

    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.paths import generate
    from mjx_pathtrack.robots import registry as robots

    loaded = robots.load_robot("armar4")
    joints = np.flatnonzero(loaded.path_mask)
    directory = datasets.dataset_dir("armar4", "random", root)
    splits = {}
    for split, count, seed in (("train", n_train, 0), ("test", n_test, 1)):
        splits[split] = generate.random_paths(loaded.limits, count, seed, in_collision=None, path_joints=joints)
        datasets.save_split(directory / f"{split}.npz", splits[split])
    datasets.write_config(directory / "config.json", dict(
        format_version=datasets.FORMAT_VERSION, robot="armar4", kind="random", n_joints=len(joints),
        joint_names=[loaded.joint_names[i] for i in joints],
        max_dis_between_knots=datasets.max_dis_between_knots(splits.values()), num_train=n_train, num_test=n_test,
        source={"type": "random_agent", "seed": 0, "steps": 80, "dt": 0.1, "substeps": 24,
                "resampling_distance": 0.1, "curvature_sampling_distance": 0.3, "collision_check": "none"}))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="/tmp/balance_splines")
    parser.add_argument("--out", default="runs/balance_evidence")
    parser.add_argument("--legs", default="controlled", choices=("fixed", "controlled"))
    parser.add_argument("--num-timesteps", type=int, default=30000)
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--eval-episodes", type=int, default=32)
    parser.add_argument("--n-train", type=int, default=64)
    parser.add_argument("--n-test", type=int, default=32)
    parser.add_argument("--batch-size", type=int, default=None, help="PPO minibatch size (default: --num-envs)")
    parser.add_argument("--scales", nargs="+", default=["1.0", "0.0"], help="balance-reward scales to train")
    parser.add_argument("--uncensored", action="store_true",
                        help="also evaluate with evaluate.py --terminate-deviation inf")
    args, train_args = parser.parse_known_args()
    root = Path(args.root)
    if not (root / "armar4" / "random" / "config.json").is_file():
        make_dataset(root, args.n_train, args.n_test)
    rates = {}
    for scale in args.scales:
        out = Path(args.out) / f"{args.legs}_balance_reward_{scale}"
        if not (out / "report.json").is_file():
            cmd = [sys.executable, str(REPO / "train.py"), "--task", "balance", "--legs", args.legs,
                   "--balance-reward", scale, "--dataset-root", str(root), "--num-envs", str(args.num_envs),
                   "--batch-size", str(args.batch_size or args.num_envs), "--num-minibatches", "4",
                   "--unroll-length", "10", "--num-timesteps", str(args.num_timesteps), "--num-evals", "2",
                   "--eval-episodes", str(args.eval_episodes), "--out", str(out), *train_args]
            print(" ".join(cmd), flush=True)
            subprocess.run(cmd, check=True)
        report = json.loads((out / "report.json").read_text())
        rates[scale] = [report["before"]["task_failed"], report["after"]["task_failed"]]
        if args.uncensored:
            ev = out / "eval_uncensored"
            cmd = [sys.executable, str(REPO / "evaluate.py"), str(out), "--terminate-deviation", "inf", "--no-toppra",
                   "--timing-decisions", "0", "--out", str(ev)]
            print(" ".join(cmd), flush=True)
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            rates[scale].append(json.loads((ev / "metrics.json").read_text())["task_failed_rate"])
    for scale, values in rates.items():
        line = (f"balance reward x{scale}: fell in {100 * values[0]:.1f} % of test episodes before training, "
                f"{100 * values[1]:.1f} % after")
        if len(values) > 2:
            line += f", {100 * values[2]:.1f} % after without the deviation limit"
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
