"""Physics steps per second of batched (vmapped) ``mjx.step`` on CPU, per robot scene.

Run: python benchmarks/bench_mjx.py [--batch 1024] [--steps 240] [--robots iiwa iiwa_ball armar4_legs]
     [--no-flag-steps 1]

Each robot is measured with the XLA CPU flag ``--xla_cpu_use_fusion_emitters=false`` (set by
``mjx_pathtrack.prepare_xla()``) and, in a subprocess with ``MJX_PATHTRACK_NO_XLA_FLAGS=1``, without it
(that variant is ~1000x slower, so it runs only ``--no-flag-steps`` steps, default 1). One physics step =
one ``mjx.step`` of every environment in the batch; the number printed is batch * steps / s,
excluding compilation. The controls hold the initial pose (the cost of a step does not depend on
the setpoints). Floor: iiwa >= 100,000 physics steps/s on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import mjx_pathtrack

mjx_pathtrack.prepare_xla()  # before JAX starts: the CPU flag batched MJX needs
import jax
import jax.numpy as jnp
from mujoco import mjx

from mjx_pathtrack.robots.registry import load_robot

IIWA_FLOOR = 100_000


def measure(name: str, batch: int, steps: int) -> dict:
    """Compile a jitted ``steps``-long ``lax.scan`` of vmapped ``mjx.step`` and time one run."""
    robot = load_robot(name)
    model = robot.mjx_model
    data = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), robot.mjx_data())

    @jax.jit
    def rollout(d):
        def body(d, _):
            return jax.vmap(mjx.step, in_axes=(None, 0))(model, d), None

        return jax.lax.scan(body, d, None, length=steps)[0]

    t0 = time.perf_counter()
    rollout = rollout.lower(data).compile()  # ahead of time: the timed call runs only
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(rollout(data))
    seconds = time.perf_counter() - t0
    finite = bool(jnp.all(jnp.isfinite(out.qpos)))
    return {"robot": name, "batch": batch, "steps": steps, "steps_per_s": batch * steps / seconds,
            "compile_s": compile_s, "finite": finite}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=240, help="physics steps per timed run (with flag)")
    parser.add_argument("--no-flag-steps", type=int, default=1, help="physics steps without the flag (0: skip)")
    parser.add_argument("--robots", nargs="+", default=["iiwa", "iiwa_ball", "armar4_legs"])
    parser.add_argument("--json", action="store_true", help="print one JSON line per robot (used internally)")
    args = parser.parse_args()

    results = [measure(name, args.batch, args.steps) for name in args.robots]
    if args.json:
        for r in results:
            print(json.dumps(r))
        return
    slow = {}
    if args.no_flag_steps > 0:
        env = {**os.environ, "MJX_PATHTRACK_NO_XLA_FLAGS": "1"}
        env["XLA_FLAGS"] = " ".join(t for t in env.get("XLA_FLAGS", "").split() if "fusion_emitters" not in t)
        cmd = [sys.executable, __file__, "--json", "--no-flag-steps", "0", "--batch", str(args.batch),
               "--steps", str(args.no_flag_steps), "--robots", *args.robots]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        for line in proc.stdout.splitlines():
            if line.startswith("{"):
                r = json.loads(line)
                slow[r["robot"]] = r
    print(f"device: {jax.devices()[0].platform}  cores: {os.cpu_count()}  batch {args.batch}  "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print(f"{'robot':<13}{'steps/s (flag)':>16}{'compile s':>11}{'steps/s (no flag)':>19}{'ratio':>9}")
    for r in results:
        s = slow.get(r["robot"])
        no_flag = f"{s['steps_per_s']:19,.0f}" if s else f"{'-':>19}"
        ratio = f"{r['steps_per_s'] / s['steps_per_s']:9.0f}" if s else f"{'-':>9}"
        print(f"{r['robot']:<13}{r['steps_per_s']:16,.0f}{r['compile_s']:11.1f}{no_flag}{ratio}"
              + ("" if r["finite"] else "  NON-FINITE STATE"))
    iiwa = next((r for r in results if r["robot"] == "iiwa"), None)
    if iiwa is not None:
        verdict = "OK" if iiwa["steps_per_s"] >= IIWA_FLOOR else "BELOW FLOOR"
        print(f"iiwa floor {IIWA_FLOOR:,} physics steps/s: {verdict}")


if __name__ == "__main__":
    main()
