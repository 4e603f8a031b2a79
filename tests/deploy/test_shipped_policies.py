"""The trained policies shipped in ``policies/`` (policies/README.md): each loads with today's
code as a run directory and as an export, the two act alike, the iiwa policy tracks its test
paths whatever their knot spacing, and the ball policy still balances
the ball on test paths, the ARMAR-4 policies track their target-point paths and the one with
controlled legs keeps the robot standing. A change to the observation, the action mapping or the export format
that would silently invalidate them fails here."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.deploy.export import load_policy
from mjx_pathtrack.evaluation import report as R

REPO = Path(__file__).resolve().parents[2]
POLICIES = sorted(p for p in (REPO / "policies").iterdir() if (p / "config.json").is_file())


def test_policies_are_shipped():
    assert [p.name for p in POLICIES] == ["armar4_balance_controlled", "armar4_target_point", "ball_on_plate", "iiwa"]


@pytest.mark.parametrize("run", POLICIES, ids=lambda p: p.name)
def test_the_run_directory_and_its_export_give_the_same_actions(run):
    from_run, from_export = R.load_policy_source(str(run)), R.load_policy_source(str(run / "export"))
    assert from_export.config == from_run.config
    size = load_policy(run / "export").observation_size
    obs = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (32, size)), jnp.float32)
    key = jax.random.PRNGKey(0)
    a_run = np.clip(np.asarray(from_run.policy(obs, key)), -1, 1)
    # float32 in another evaluation order (the export is compiled on its own): up to 2e-5 here
    np.testing.assert_allclose(np.asarray(from_export.policy(obs, key)), a_run, rtol=1e-5, atol=1e-4)
    assert np.std(a_run) > 0.05  # a trained policy, not a constant


@pytest.mark.parametrize("run", POLICIES, ids=lambda p: p.name)
def test_the_shipped_onnx_graph_gives_the_exports_actions(run):
    """``export/policy.onnx`` acts as ``policy.jaxexport`` within 1e-5 on 10,000 observations;
    a policy without one says why in its manifest (the iiwa and ball policies must have one)."""
    from mjx_pathtrack.deploy.onnx_policy import OnnxPolicy, max_difference

    exported = load_policy(run / "export")
    entry = exported.manifest.get("onnx")
    assert entry is not None, f"{run.name}: no onnx entry (python scripts/attach_onnx.py {run.relative_to(REPO)})"
    if entry["file"] is None:
        assert run.name not in ("iiwa", "ball_on_plate") and entry["reason"]
        assert not (run / "export" / "policy.onnx").exists()
        return
    assert max_difference(OnnxPolicy(run / "export" / entry["file"]), exported, seed=11) <= 1e-5


def _evaluate(tmp_path, *args):
    out = tmp_path / "eval"
    subprocess.run([sys.executable, "evaluate.py", *args, "--no-toppra", "--timing-decisions", "0", "--out", str(out)],
                   cwd=REPO, check=True, capture_output=True, text=True)
    return json.loads((out / "metrics.json").read_text())


def test_the_shipped_armar4_policy_tracks_target_point_paths(tmp_path):
    """16 test sub-paths on the fixed base, deterministic export: the full evaluation (200
    sub-paths) reaches the end in 89.5 % at 0.112 rad mean joint deviation; a policy that does
    not track reaches none."""
    m = _evaluate(tmp_path, "policies/armar4_target_point/export", "--episodes", "16")
    assert m["episodes"] == 16 and m["robot"] == "armar4"
    assert m["end_reached_rate"] >= 12 / 16 and m["joint_dev_mean"] < 0.15
    assert m["limit_audit"]["ok"]


@pytest.mark.slow
def test_the_shipped_ball_policy_balances_the_ball_on_test_paths(tmp_path):
    """16 whole test paths in the rolling-ball (training) scene, deterministic export: the full
    evaluation (200 paths, docs/results.md) drops the ball in 0.5 % and reaches the end in 99.5 %."""
    m = _evaluate(tmp_path, "policies/ball_on_plate/export", "--full-paths", "--episodes", "16")
    assert m["episodes"] == 16 and m["ball_physics"] == "rolling"
    assert m["task_failed_rate"] <= 1 / 16 and m["end_reached_rate"] >= 15 / 16
    assert m["end_time_s_mean"] < 3.5 and m["cart_pos_dev_cm_mean"] < 3.0
    assert m["limit_audit"]["ok"]


@pytest.mark.slow
def test_the_shipped_armar4_balance_policy_tracks_standing_on_its_legs(tmp_path):
    """8 test sub-paths standing on the floor with controlled legs (the leg prior included in the
    export), deterministic: the full evaluation (200 sub-paths, docs/results.md "Table VIII")
    reaches the end in 82.5 % and falls in 7.0 %; a policy whose legs drift falls in most."""
    m = _evaluate(tmp_path, "policies/armar4_balance_controlled/export", "--episodes", "8")
    assert m["episodes"] == 8 and "robot_fell_rate" in m["task_failures"]
    assert m["task_failed_rate"] <= 1 / 8 and m["end_reached_rate"] >= 6 / 8 and m["joint_dev_mean"] < 0.15
    assert m["limit_audit"]["ok"]


def test_the_shipped_iiwa_policy_tracks_its_test_paths(tmp_path):
    """16 test sub-paths of the mixed set (random and smooth target point), deterministic export:
    the full evaluation (200 sub-paths, docs/results.md "Any path a user brings") reaches the end
    in END_200; a policy that does not track reaches none."""
    m = _evaluate(tmp_path, "policies/iiwa/export", "--episodes", "16")
    assert m["episodes"] == 16 and m["robot"] == "iiwa" and m["paths"] == "iiwa/mixed/test"
    assert m["end_reached_rate"] >= 14 / 16 and m["joint_dev_mean"] < 0.12
    assert m["limit_audit"]["ok"]


@pytest.mark.slow
def test_one_curve_gives_one_result_whatever_its_knots(tmp_path):
    """The same 16 test curves of the shipped iiwa policy, whole, given with their own knots,
    with waypoints every 0.03 rad, every third of those and uniformly every 0.15 rad: re-knotted
    by the policy's rule, each spacing reaches the end in as many episodes (within one) at the
    same duration ratio to TOPP-RA (within 3 %), batched and jitted as evaluate.py runs them; and
    the online tracker takes the dense waypoints to the end like the curve's own knots."""
    from mjx_pathtrack.core.spline_fit import fit_spline
    from mjx_pathtrack.deploy.controller import OnlineTracker, Status
    from mjx_pathtrack.paths import datasets

    source = R.load_policy_source(str(REPO / "policies/iiwa/export"))
    native = datasets.load_split("iiwa", "mixed", "test")[:16]
    results = {}
    for spacing in (None, 0.03, 0.09, 0.15):
        given = native if spacing is None else [
            f.point_at(np.append(np.arange(0.0, f.length, spacing), f.length)) for f in map(fit_spline, native)]
        file = tmp_path / f"paths_{spacing}.npz"
        datasets.save_split(file, given)
        user = R.load_user_paths(str(file), "iiwa", None if spacing is None else source.training_knot_rule(),
                                 cartesian=False)
        env, robot, _ = R.build_env(source, user, full_paths=True)
        summary, table, _ = R.run_evaluation(env, source.policy, robot, timing_decisions=0, measure=user.curves)
        results[spacing] = (int(np.sum(table["end_reached"])), summary["ratio_to_toppra_mean"])
    ends, ratio = results[None]
    assert ends >= 14, results
    for spacing, (e, r) in results.items():
        assert abs(e - ends) <= 1 and abs(r / ratio - 1) <= 0.03, (spacing, results)
    # the online tracker on the first curve: own knots and dense waypoints, same time to the end
    policy = load_policy(REPO / "policies/iiwa/export")
    times = []
    fit = fit_spline(native[0])
    dense = fit.point_at(np.append(np.arange(0.0, fit.length, 0.03), fit.length))
    for knots in (native[0], dense):
        t = OnlineTracker(policy, knots[0], controller_dt=0.01, keep_knots=knots is native[0])
        t.set_path(knots)
        for step in range(200):
            out = t.step()
            if out.status is Status.STOPPED:
                break
        assert out.reached_end and out.status is Status.STOPPED
        times.append(step)
    assert abs(times[1] - times[0]) <= max(2, 0.03 * times[0]), times
