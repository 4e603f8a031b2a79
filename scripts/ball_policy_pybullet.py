"""A ball policy's own plate motions replayed in the papers' simulator (PyBullet), open loop.

Runs the trained policy (deterministic) on the ball task's test paths in the rolling-ball scene it
trained in, records the plate motion of every physics step, and replays it in PyBullet with the
same balls (``tests/pybullet_ball.py``: 240 Hz, 50 solver iterations). The policy does not see
PyBullet's ball (open loop), so this asks: under the motions the policy makes, does the papers'
simulator's ball fall where the training scene's does? By default the replay prescribes the
plate from the setpoints, as the training scene does; ``--arm`` lets PyBullet simulate the iiwa
carrying the plate under position control towards the setpoints (the papers' robot: target
velocities 0.87 v). docs/results.md "Ball on plate".

    python scripts/ball_policy_pybullet.py runs/ball [--episodes 200] [--arm]

PyBullet is a test extra (``pip install -e ".[test]"``), never used in training.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mjx_pathtrack  # noqa: E402

mjx_pathtrack.prepare_xla()
import jax  # noqa: E402
import numpy as np  # noqa: E402

from mjx_pathtrack.evaluation import report as R  # noqa: E402
from mjx_pathtrack.evaluation import rollout as E  # noqa: E402
from mjx_pathtrack.envs.tasks import ball_on_plate as BP  # noqa: E402
from mjx_pathtrack.robots import ball_scene as B  # noqa: E402
from mjx_pathtrack.robots.registry import IIWA_URDF  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import pybullet_ball  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="run directory of a ball_on_plate run")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arm", action="store_true",
                        help="PyBullet also simulates the arm (position control towards the setpoints, the papers' robot) "
                             "instead of prescribing the plate")
    args = parser.parse_args()
    source = R.load_policy_source(args.run)
    if source.config.task != "ball_on_plate":
        print(f"{args.run}: task {source.config.task!r}, not ball_on_plate", file=sys.stderr)
        return 2
    source = dataclasses.replace(source, config=source.config.replace(ball_physics="rolling"))
    env, _, label = R.build_env(source)
    indices = np.arange(args.episodes) % len(env.paths.n_knots)
    rng = jax.random.PRNGKey(args.seed)
    ro = E.rollout(env, source.policy, rng, indices)
    start = E.reset_episodes(env, rng, len(indices), jax.numpy.asarray(indices, jax.numpy.int32))[0].pipeline_state.executor
    radius, mass = (np.asarray(x) for x in jax.vmap(B.sample_ball)(start.key))
    spin, roll = (np.asarray(x) for x in jax.vmap(BP.sample_friction)(start.key))
    xy = np.asarray(start.ball)[:, :2]
    fell_rolling = np.asarray(ro.metrics.task_failed) > 0
    plate_pose = jax.jit(jax.vmap(env.executor.plate_pose))
    half = np.asarray(BP.R.BALL_HALF_RANGE)
    fell_pybullet, t0 = [], time.monotonic()
    for b in range(len(indices)):
        q = E.executed_polyline(ro, b)  # setpoints of every physics step the episode ran
        ball = dict(radius=float(radius[b]), mass=float(mass[b]), mu_roll=float(roll[b]),
                    mu_spin=float(spin[b]), substeps=env.executor.substeps)
        if args.arm:
            seen = pybullet_ball.replay_arm(str(IIWA_URDF), env.executor.robot.joint_names, np.asarray(q, np.float64),
                                            xy[b], **ball)
        else:
            surface, rot = (np.asarray(x, np.float64) for x in plate_pose(jax.numpy.asarray(q, jax.numpy.float32)))
            seen = pybullet_ball.replay(surface, rot, xy[b], **ball)
        fell_pybullet.append(bool(np.any(np.any(np.abs(seen[:, :2] / half) >= 1.0, axis=-1) | (seen[:, 2] < 0.0))))
    fell_pybullet = np.array(fell_pybullet)
    how = "its setpoints replayed open loop on PyBullet's position-controlled arm" if args.arm else \
        "its plate motions replayed open loop in PyBullet"
    print(f"{args.run} on {label}, {len(indices)} episodes, deterministic policy in the rolling-ball scene, "
          f"{how} ({time.monotonic() - t0:.0f} s):")
    print(f"ball fell: rolling (closed loop) {fell_rolling.mean():.1%}   PyBullet (open loop, same motions) "
          f"{fell_pybullet.mean():.1%}   same outcome {(fell_rolling == fell_pybullet).mean():.1%}   "
          f"PyBullet only {(fell_pybullet & ~fell_rolling).mean():.1%}   rolling only {(fell_rolling & ~fell_pybullet).mean():.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
