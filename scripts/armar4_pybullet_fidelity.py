"""ARMAR-4 with its legs held: does our model tilt and fall where the papers' simulator does?

Replays the same upper-body setpoint trajectories (240 Hz) on the floating-base ARMAR-4 (legs
held at their start pose by their servos) in our model and in PyBullet with the papers' settings
(the oracle: ``tests/pybullet_armar4.py``) and compares the pelvis tilt (angle of the base's z
axis to the vertical). Motions, all starting at rest from the robot's start pose:

* ``toppra``: the ARMAR-4 target-point test paths traversed time-optimally (TOPP-RA with the
  velocity and acceleration limits; no jerk limit, so faster than any policy), then held 1 s;
* ``bang``: bang-bang actions (+-1 per joint, each sign kept for 1-6 decision steps) mapped into
  the safe acceleration range: jerk-limited, at the limits;
* ``random``: the random agent (actions U(-1, 1)), the gentlest.

A motion "falls" when the tilt exceeds the balance task's ``FALL_TILT`` (0.52 rad). The peak
ratio compares the largest tilt change from rest (PyBullet's mesh feet stand 0.006 rad tilted)
over the motions neither model falls in.

    python scripts/armar4_pybullet_fidelity.py [--motions 40] [--paths 20] [--seconds 4] [--json out.json]
        [--model armar4_legs armar4_standing armar4_standing@80]

``--model`` names our models to compare (registry robots; ``@HZ``: physics rate instead of 240
Hz, a divisor of 240, with the registry's servo bandwidth for it; ``@HZ:OMEGA``: and servos of
bandwidth OMEGA rad/s): ``armar4_legs`` (legs held by their servos, the default),
``armar4_standing`` (legs welded; the balance task runs it at 80 Hz: ``armar4_standing@80``).

PyBullet is a test extra (``pip install -e ".[test]"``), never used in training.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mjx_pathtrack  # noqa: E402

mjx_pathtrack.prepare_xla()
import jax  # noqa: E402
import numpy as np  # noqa: E402

from mjx_pathtrack.core import limits as L  # noqa: E402
from mjx_pathtrack.envs.tasks.humanoid_balance import FALL_TILT  # noqa: E402
from mjx_pathtrack.paths import datasets  # noqa: E402
from mjx_pathtrack.robots.registry import load_robot  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from pybullet_armar4 import HZ, PyBulletArmar4, agent_motions, load_model, mujoco_tilts, toppra_motion  # noqa: E402

def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--motions", type=int, default=10, help="bang-bang and random motions each")
    parser.add_argument("--paths", type=int, default=20, help="target-point test paths (TOPP-RA)")
    parser.add_argument("--seconds", type=float, default=4.0, help="length of the bang-bang and random motions")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="write the per-motion peak tilts here")
    parser.add_argument("--model", nargs="+", default=["armar4_legs"],
                        help="our models: registry robot names, optionally @HZ (physics rate) or @HZ:OMEGA "
                             "(and servo bandwidth [rad/s])")
    args = parser.parse_args()
    ours_models = {spec: load_model(spec) for spec in args.model}
    robot = load_robot("armar4_legs")  # motions and the oracle: the 18 upper-body joints of the full robot
    upper = np.flatnonzero(robot.path_mask)
    lim = robot.limits
    sub = L.JointLimits(*(np.asarray(x)[upper] for x in (lim.pos_min, lim.pos_max, lim.vel, lim.acc, lim.jerk)))
    motions = []
    for i, knots in enumerate(datasets.load_split("armar4", "target_point", "test")[:args.paths]):
        motions.append(("toppra", i, *toppra_motion(np.asarray(knots, np.float64), np.asarray(sub.vel), np.asarray(sub.acc))))
    p0 = np.asarray(robot.q0)[upper]
    for kind, bang, seed in (("bang", True, args.seed), ("random", False, args.seed + 1)):
        qs, vs = agent_motions(sub, p0, jax.random.PRNGKey(seed), args.motions, args.seconds, bang)
        motions += [(kind, i, q, v) for i, (q, v) in enumerate(zip(qs, vs))]
    bullet = PyBulletArmar4(robot)
    rows = []
    t0 = time.monotonic()
    for kind, i, q, v in motions:
        theirs = bullet.tilts(upper, q, v)
        row = {"kind": kind, "index": i, "seconds": len(q) / HZ, "peak_pybullet": float(theirs.max()),
               "rest_pybullet": float(theirs[0]), "fell_pybullet": bool(theirs.max() > FALL_TILT)}
        for spec, ours_robot in ours_models.items():
            ours = mujoco_tilts(ours_robot, np.flatnonzero(ours_robot.path_mask), q, v)
            row.update({f"peak_{spec}": float(ours.max()), f"rest_{spec}": float(ours[0]),
                        f"fell_{spec}": bool(ours.max() > FALL_TILT)})
        rows.append(row)
        print(f"{kind:7s}{i:3d}  {row['seconds']:5.2f} s  peak tilt pybullet {row['peak_pybullet']:.4f}  "
              + "  ".join(f"{spec} {row[f'peak_{spec}']:.4f}" for spec in ours_models) + " rad", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    print(f"\n{len(rows)} motions in {time.monotonic() - t0:.0f} s; fall threshold {FALL_TILT} rad; "
          f"tilt at rest pybullet {np.mean([r['rest_pybullet'] for r in rows]):.4f} rad")
    print("peak ratio: median over the motions neither falls in of (peak - tilt at rest), ours / pybullet")
    for spec in ours_models:
        print(f"ours = {spec} (tilt at rest {np.mean([r[f'rest_{spec}'] for r in rows]):.4f} rad)")
        for kind in ("toppra", "bang", "random", None):
            sel = [r for r in rows if r["kind"] == kind or kind is None]
            if not sel:
                continue
            agree = np.mean([r[f"fell_{spec}"] == r["fell_pybullet"] for r in sel])
            up = [r for r in sel if not (r[f"fell_{spec}"] or r["fell_pybullet"])]
            rise = lambda r, who: max(r[f"peak_{who}"] - r[f"rest_{who}"], 1e-6)  # noqa: E731
            ratio = np.median([rise(r, spec) / rise(r, "pybullet") for r in up])
            print(f"  {kind or 'all':7s} {len(sel):3d} motions   falls ours {np.mean([r[f'fell_{spec}'] for r in sel]):4.0%}  "
                  f"pybullet {np.mean([r['fell_pybullet'] for r in sel]):4.0%}   same outcome {agree:4.0%}   "
                  f"peak ratio {ratio:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
