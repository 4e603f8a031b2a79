"""Does ARMAR-4 with fixed legs fall at all? Replays random safe upper-body motions (the random
agent of the datasets: actions U(-1, 1) mapped into the safe acceleration range, 240 Hz setpoints)
on the floating-base ``armar4_legs`` model in MuJoCo C, legs held at q0, and prints the largest
pelvis tilt per motion (the balance task counts a fall beyond 0.52 rad).

    python scripts/balance_fixed_legs_check.py [--motions 16] [--steps 60]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mjx_pathtrack  # noqa: E402

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from mjx_pathtrack.paths import generate  # noqa: E402
from mjx_pathtrack.core import limits as L  # noqa: E402
from mjx_pathtrack.robots.registry import load_robot  # noqa: E402
from mjx_pathtrack.envs.tasks.humanoid_balance import FALL_TILT  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--motions", type=int, default=16)
    parser.add_argument("--steps", type=int, default=60, help="decision steps (0.1 s) per motion")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    robot = load_robot("armar4_legs")
    model, lim = robot.mj_model, robot.limits
    upper = np.flatnonzero(robot.path_mask)
    sub = L.JointLimits(*(np.asarray(x)[upper] for x in (lim.pos_min, lim.pos_max, lim.vel, lim.acc, lim.jerk)))
    motions = np.asarray(generate.random_motions(sub, jax.random.PRNGKey(args.seed), args.motions, args.steps,
                                                 robot.dt, robot.n_substeps))
    sim_dt = model.opt.timestep
    tilts = []
    for motion in motions:
        data = robot.mj_data()
        q = np.asarray(robot.q0, np.float64).copy()
        q[upper] = motion[0]
        data.qpos[robot.qpos_adr] = q
        mujoco.mj_forward(model, data)
        worst = 0.0
        for i in range(len(motion) - 1):
            v = np.zeros(robot.n_joints)
            q[upper], v[upper] = motion[i], (motion[i + 1] - motion[i]) / sim_dt
            data.ctrl[:] = np.concatenate([q, v])
            mujoco.mj_step(model, data)
            z = data.xmat[1].reshape(3, 3)[:, 2]
            worst = max(worst, float(np.arccos(np.clip(z[2], -1.0, 1.0))))
        tilts.append(worst)
    tilts = np.asarray(tilts)
    print(f"{args.motions} random upper-body motions of {args.steps * robot.dt:.1f} s, legs fixed: largest pelvis tilt "
          f"per motion [rad] {np.round(tilts, 3).tolist()}; fell (> {FALL_TILT} rad) in {np.mean(tilts > FALL_TILT):.0%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
