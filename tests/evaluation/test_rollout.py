"""Evaluation metrics on hand-made episodes with known answers, the limit audit, the computation
time, and evaluate.py on a tiny run directory (parameters built without training) and bad inputs."""

import dataclasses
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mjx_pathtrack  # noqa: F401
import jax
import jax.numpy as jnp

from mjx_pathtrack.evaluation import baseline
from mjx_pathtrack.evaluation import report as R
from mjx_pathtrack.evaluation import geometry as G
from mjx_pathtrack.evaluation import rollout as E
from mjx_pathtrack.robots import registry as robots
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.paths.datasets import DatasetError
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.config.stored import PARAMS_FILE, params_bytes
from mjx_pathtrack.deploy.networks import networks as ppo_networks
from mjx_pathtrack.rl.training import make_env

REPO = Path(__file__).resolve().parents[2]
DT = 0.1
SHOULDER = 0.5  # joint 2 held here, so that the tool point is off the joint-1 axis


def _line(length):
    knots = np.zeros((6, 7))
    knots[:, 0] = np.linspace(0.0, length, 6)
    knots[:, 1] = SHOULDER
    return S.make_path(knots)


def _joint0_policy(obs, key):
    """Joint 1 (index 0) as fast as allowed, the others in mid-range (held at rest)."""
    return jnp.zeros((obs.shape[0], 7)).at[:, 0].set(1.0)


@pytest.fixture(scope="module")
def iiwa():
    return robots.load_robot("iiwa", dt=DT)


@pytest.fixture(scope="module")
def lines(iiwa):
    """Whole-path episodes along joint 1 on a 1 rad line (reaches the end, brakes, stops) and a
    4 rad line (the 1.5 s budget ends first), with the analytic joint-1 policy."""
    cfg = EnvConfig(start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0, terminate_deviation=None,
                    duration=1.5)
    env = PathTrackingEnv(iiwa.limits, S.stack_paths([_line(1.0), _line(4.0)]), 0.9, cfg, home=iiwa.q0)
    ro = E.rollout(env, _joint0_policy, jax.random.PRNGKey(0), [0, 1])
    return env, ro, E.episode_table(env, ro, iiwa)


def test_line_followed_exactly_has_zero_deviation(lines):
    _, _, t = lines
    assert t["termination"][1] == "time_budget" and not t["end_reached"][1] and np.isnan(t["stop_time_s"][1])
    assert t["n_samples"][1] > 150  # > 1.5 rad travelled, sampled every 0.01 rad
    assert t["joint_dev_max"][1] < 1e-5
    assert t["cart_pos_dev_cm_max"][1] < 1e-3 and t["cart_rot_dev_deg_max"][1] < 0.1
    assert t["cart_contour_dev_cm_max"][1] < 1e-3


def test_overshoot_after_the_end_gives_the_known_deviations(lines, iiwa):
    """After the end the robot brakes and overshoots it by ``o``: the reference there is the end
    knot, so the deviation is ``max(0, s - 1)`` along the path: final ~``o``, mean ~``o^2 / 2(1 + o)``;
    the tool point is rotated by ``o`` about the vertical base axis: position ``2 r sin(o/2)``,
    orientation ``o``."""
    _, ro, t = lines
    assert t["termination"][0] == "stopped_at_end" and t["end_reached"][0]
    o = float(ro.p[ro.live[:, 0], 0][-1, 0]) - 1.0
    assert 0.01 < o < 0.2
    assert t["success"][0] == (o < 0.05)  # success: stopped within 0.05 rad of the end knot
    # samples every 0.01 rad up to the travelled 1 + o; the last one is the final value
    s = 0.01 * np.arange(1, int(np.floor((1.0 + o) / 0.01 + 1e-6)) + 1)
    dev = np.maximum(s - 1.0, 0.0)
    assert t["n_samples"][0] == len(s)
    assert t["joint_dev_final"][0] == pytest.approx(dev[-1], abs=1e-4)
    assert t["joint_dev_max"][0] == pytest.approx(dev[-1], abs=1e-4)
    assert t["joint_dev_mean"][0] == pytest.approx(dev.mean(), abs=1e-4)
    assert dev.mean() == pytest.approx(o * o / (2 * (1 + o)), abs=2e-3)
    o = dev[-1]  # the overshoot at the final sample
    x = np.asarray(iiwa.fk(jnp.zeros(7).at[1].set(SHOULDER))[0])[0]
    r = float(np.hypot(x[0], x[1]))
    assert r > 0.3
    assert t["cart_pos_dev_cm_final"][0] == pytest.approx(100 * 2 * r * np.sin(o / 2), rel=2e-3)
    assert t["cart_rot_dev_deg_final"][0] == pytest.approx(np.degrees(o), abs=0.05)
    # beyond the end the nearest point of the reference curve is its end: the same distance
    assert t["cart_contour_dev_cm_final"][0] == pytest.approx(t["cart_pos_dev_cm_final"][0], rel=2e-3)


def test_polyline_distance_with_a_kd_tree_is_exact():
    """Long curves take the KD-tree route; it must give the brute-force answer to the last bit,
    for points near the curve and far from it."""
    rng = np.random.default_rng(0)
    curve = np.cumsum(rng.normal(size=(3000, 3)) * 0.01, 0)
    points = np.concatenate([curve[rng.integers(0, 3000, 300)] + rng.normal(size=(300, 3)) * 0.003,
                             rng.normal(size=(50, 3))])
    brute = G._segment_distance(points, curve, np.arange(len(curve) - 1)[None])
    np.testing.assert_array_equal(G.polyline_distance(points, curve), brute)


def test_polyline_distance_known_answers():
    """An L-shaped polyline (0,0) -> (1,0) -> (1,1): a point beside a segment, one at the corner's
    outside, one beyond the end, one on the curve; a one-point curve is that point."""
    curve = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    points = np.array([[0.5, -0.2], [1.3, -0.4], [1.0, 1.5], [1.0, 0.25]])
    np.testing.assert_allclose(G.polyline_distance(points, curve), [0.2, 0.5, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(G.polyline_distance(points, curve[:1]), np.linalg.norm(points, axis=-1))


def test_contour_deviation_leaves_out_the_arc_length_drift(iiwa):
    """Joint 1 at full speed along the line, joint 7 (the flange's rotation about the axis the tool
    point lies on) kicked back and forth by random actions: the wiggles lengthen the executed
    joint-space path, so the equal-arc comparison drifts behind along the line, but the tool point
    never leaves the reference's curve. The contour deviation stays ~0 while the paper's Cartesian
    deviation (at equal arc length) grows."""
    lim = iiwa.limits
    home = -1.0 + 2.0 * (0.0 - float(lim.pos_min[6])) / float(lim.pos_max[6] - lim.pos_min[6])

    def wiggle(obs, key):  # random kicks on joint 7 about its start, held there by a PD term
        side = jnp.where(jax.random.bernoulli(key, 0.5, (obs.shape[0],)), 1.0, -1.0)
        pd = -20.0 * (obs[:, 6] - home) - 2.0 * obs[:, 7 + 6]  # obs: positions, velocities, ... (normalised)
        return jnp.zeros((obs.shape[0], 7)).at[:, 0].set(1.0).at[:, 6].set(jnp.clip(pd + 0.6 * side, -1.0, 1.0))

    cfg = EnvConfig(start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0, terminate_deviation=None,
                    duration=1.5)
    env = PathTrackingEnv(iiwa.limits, S.stack_paths([_line(4.0)] * 2), 0.9, cfg, home=iiwa.q0)
    t = E.episode_table(env, E.rollout(env, wiggle, jax.random.PRNGKey(3), [0, 1]), iiwa)
    assert np.all(t["joint_dev_mean"] > 0.02)  # the wiggle does drift
    assert np.all(t["cart_pos_dev_cm_mean"] > 0.5)
    assert np.all(t["cart_contour_dev_cm_max"] < 2e-3)  # float32 FK


def test_durations_of_the_line_against_the_bang_bang_profile(lines):
    """Full speed along a 1 rad line: the end is reached no earlier than the acceleration-limited
    profile (accelerate, cruise: L/v + v/2a) and at most 2 steps later (jerk ramps, decision grid);
    stopping takes longer than TOPP-RA's rest-to-rest time, by less than 50 %."""
    env, ro, t = lines
    v, a = float(env.limits.vel[0]), float(env.limits.acc[0])
    reach = 1.0 / v + v / (2 * a)
    assert reach <= t["end_time_s"][0] <= reach + 2 * DT
    assert t["stop_time_s"][0] == pytest.approx(t["steps"][0] * DT)
    topp = baseline.baseline_durations(ro.paths, ro.s_start, np.asarray(env.limits.vel), np.asarray(env.limits.acc))
    assert topp[0] == pytest.approx(baseline.bang_bang_duration(1.0, v, a), rel=2e-3)
    ratio = baseline.duration_ratio(t["stop_time_s"], topp)
    assert ratio[0] > 1.0 and ratio[0] < 1.5 and np.isnan(ratio[1])


def test_limit_audit_and_aggregate(lines):
    _, _, t = lines
    summary = E.aggregate(t)
    audit = summary["limit_audit"]
    assert audit["ok"] and max(audit[q] for q in ("pos", "vel", "acc", "jerk")) <= 1 + E.AUDIT_TOLERANCE
    assert audit["vel"] > 0.99 and audit["acc"] > 0.9  # the limits were used, not just respected
    assert summary["end_reached_rate"] == 0.5 and summary["termination"]["time_budget"] == 0.5
    assert summary["stop_time_s_mean"] == pytest.approx(float(t["stop_time_s"][0]))
    assert summary["joint_dev_max"] == pytest.approx(float(t["joint_dev_max"].max()))
    json.dumps(summary)  # plain JSON types


def test_limit_ratios_flag_a_violation():
    from mjx_pathtrack.robots import iiwa as I

    lim = I.joint_limits(DT)
    v = jnp.zeros(7).at[2].set(float(I.VEL[2]) * 0.99)
    # accelerating on through the velocity limit within the step: the in-step maximum is > 1
    r = np.asarray(E.limit_ratios(lim, jnp.zeros(7), v, jnp.zeros(7), jnp.zeros(7).at[2].set(2.0), DT))
    assert r.shape == (4, 7) and r[1, 2] > 1.0 and r[1, 2] == pytest.approx(
        (0.99 * I.VEL[2] + 0.5 * 2.0 * DT) / I.VEL[2], rel=1e-5)
    assert r[2, 2] == pytest.approx(2.0 / I.ACC[2], rel=1e-6) and r[3, 2] == pytest.approx(20.0 / float(lim.jerk[2]))


# -- evaluate.py ---------------------------------------------------------------------------------


def _write_run(run: Path, layers=(16,), **options):
    """A run directory with untrained (random) parameters: config.json + params.msgpack (``options``:
    flat options of the run's config)."""
    from brax.training.acme import running_statistics, specs

    cfg = TrainConfig().replace(policy_layers=layers, value_layers=(8,), duration=4.0, **options)
    env = make_env(cfg, "test")
    nets = ppo_networks(cfg.network)(env.observation_size, env.action_size,
                             preprocess_observations_fn=running_statistics.normalize)
    key = jax.random.PRNGKey(0)
    norm = running_statistics.init_state(specs.Array((env.observation_size,), jnp.dtype("float32")))
    params = (norm, nets.policy_network.init(key), nets.value_network.init(key))
    run.mkdir(parents=True, exist_ok=True)
    (run / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    (run / PARAMS_FILE).write_bytes(params_bytes(jax.tree.map(np.asarray, params)))
    return cfg, env, nets, params


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("eval") / "run"
    return run, _write_run(run)


@pytest.mark.slow
def test_evaluate_cli_on_a_tiny_run(tiny_run, tmp_path):
    run, _ = tiny_run
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg")
    result = subprocess.run([sys.executable, "evaluate.py", str(run), "--episodes", "3", "--timing-decisions", "5",
                             "--terminate-deviation", "0.3", "--end-tolerance", "0.05", "--out", str(out),
                             "--video", str(out / "clip.gif"), "--video-episodes", "0", "2", "--video-size", "64x48",
                             "--video-fps", "5", "--online-baselines"],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for heading in ("Table I", "Table VI", "Table IX", "Limit audit", "OK (<= 1)"):
        assert heading in result.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["episodes"] == 3 and metrics["limit_audit"]["ok"] and metrics["paths"] == "iiwa/random/test"
    assert metrics["terminate_deviation"] == 0.3 and metrics["actions"] == "deterministic"
    assert metrics["end_tolerance"] == 0.05
    assert metrics["computation_time"]["decisions"] == 5 and 0 < metrics["computation_time"]["max_over_dt"] < 10
    assert metrics["toppra_duration_s_mean"] > 0
    rows = (out / "episodes.csv").read_text().strip().splitlines()
    assert len(rows) == 4 and "toppra_duration_s" in rows[0] and "cart_pos_dev_cm_mean" in rows[0]
    for name in ("kinematics", "joint_path", "cartesian"):
        assert (out / f"episode0_{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the online peer ran on the same episodes and is reported beside the policy
    peers = metrics["online_peers"]
    assert [r["controller"].split(" (")[0] for r in peers] == ["policy", "Ruckig look-ahead"]
    assert "Online peers on the same 3 episodes" in result.stdout
    for r in peers:   # what is printed is what metrics.json holds
        assert f"{r['controller']:<40} end {100 * r['end_reached']:5.1f} %" in result.stdout
        assert np.isfinite(r["joint_dev_mean"])
    assert peers[1]["compute_mean_ms"] > 0
    from PIL import Image

    table = np.genfromtxt(out / "episodes.csv", delimiter=",", names=True)
    for b in (0, 2):   # one video per chosen episode, one frame per 0.2 s of its motion, start included
        with Image.open(out / f"clip_episode{b}.gif") as clip:
            assert clip.size == (64, 48) and clip.n_frames == int(table["steps"][b] * 0.1 * 5 + 1e-9) + 1


def test_evaluate_cli_fails_on_a_missing_directory_before_importing_jax(tmp_path):
    """evaluate.py checks its cheap arguments before the imports that take seconds."""
    code = ("import sys, evaluate\n"
            f"rc = evaluate.main([{str(tmp_path / 'nothing')!r}])\n"
            "print('rc', rc, 'jax imported', 'jax' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert "rc 2 jax imported False" in result.stdout, result.stdout + result.stderr
    assert "no run or export directory at" in result.stderr


def test_export_dir_gives_the_same_policy(tiny_run, tmp_path):
    from brax.training.agents.ppo import networks as ppo_nets

    from mjx_pathtrack.deploy.export import export_policy

    run, (cfg, env, nets, params) = tiny_run
    export_policy(tmp_path / "export", ppo_nets.make_inference_fn(nets), params, env, "iiwa",
                  robots.load_robot("iiwa").joint_names)
    from_run, from_export = R.load_policy_source(str(run)), R.load_policy_source(str(tmp_path / "export"))
    assert from_export.kind == "export" and from_export.max_dis == pytest.approx(env.max_dis)
    obs = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (5, env.observation_size)), jnp.float32)
    key = jax.random.PRNGKey(0)
    np.testing.assert_allclose(np.asarray(from_export.policy(obs, key)), np.asarray(from_run.policy(obs, key)),
                               atol=1e-5)
    with pytest.raises(R.EvaluationError, match="only the deterministic policy"):  # an export holds the mean only
        R.load_policy_source(str(tmp_path / "export"), deterministic=False)


def test_export_records_the_run_configuration(tiny_run, tmp_path):
    """An export rebuilds its run's configuration (task, task options, environment) from the
    manifest; an older export of a task other than plain tracking is refused with a clear error."""
    import json

    from brax.training.agents.ppo import networks as ppo_nets

    from mjx_pathtrack.deploy.export import MANIFEST_FILE, export_policy

    run, (cfg, env, nets, params) = tiny_run
    ball_cfg = cfg.replace(task="ball_on_plate", dataset="ball_balancing", ball_reward=0.5, ball_physics="rolling",
                           duration=6.0)
    out = export_policy(tmp_path / "export", ppo_nets.make_inference_fn(nets), params, env, "iiwa",
                        robots.load_robot("iiwa").joint_names, ball_cfg.to_json())
    assert R.load_policy_source(str(out)).config == ball_cfg
    manifest = json.loads((out / MANIFEST_FILE).read_text())
    del manifest["run_config"]
    manifest["task"] = "ball_on_plate"
    (out / MANIFEST_FILE).write_text(json.dumps(manifest))
    with pytest.raises(R.EvaluationError, match="'ball_on_plate' task written before exports recorded"):
        R.load_policy_source(str(out))


def test_stochastic_policy_samples_around_the_deterministic_mean(tiny_run):
    run, (cfg, env, _, _) = tiny_run
    mean = R.load_policy_source(str(run)).policy
    sampled = R.load_policy_source(str(run), deterministic=False).policy
    obs = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (4096, env.observation_size)), jnp.float32)
    a, b = sampled(obs, jax.random.PRNGKey(0)), sampled(obs, jax.random.PRNGKey(1))
    assert np.all(np.asarray(a) != np.asarray(b))  # fresh noise for every key, episode and joint
    noise = np.asarray(a - mean(obs, jax.random.PRNGKey(0)))
    assert abs(noise.mean()) < 0.05 and 0.5 * cfg.network.init_noise_std < noise.std() < 2 * cfg.network.init_noise_std


@pytest.mark.slow
def test_floating_base_runs_a_plain_armar4_tracking_policy_on_the_floor(tiny_run, tmp_path):
    """``--floating-base`` (the papers' Table VIII "no balancing reward" row): the tracking run's
    policy (226 observations, no pelvis) drives the welded-legs robot standing on the floor at 80 Hz;
    the report counts falls. Other runs are refused naming the flag."""
    run = tmp_path / "armar4"
    cfg, *_ = _write_run(run, robot="armar4", dataset="target_point", n_next=8)
    source = R.load_policy_source(str(run))
    env, robot, label = R.build_env(source, full_paths=True, floating_base=True)
    assert env.task_name == "balance" and env.robot.name == "armar4_standing" and env.robot.n_substeps == 8
    assert env.observation_size == 226 and env.action_size == 18 and robot.name == "armar4"
    summary, table, _ = R.run_evaluation(env, source.policy, robot, episodes=2, timing_decisions=0, topp=False)
    assert summary["episodes"] == 2 and "task_failed_rate" in summary and summary["task_failures"]
    assert label == "armar4/target_point/test"
    with pytest.raises(R.EvaluationError, match="--floating-base: .*plain tracking run of robot 'armar4'.*'iiwa'"):
        R.build_env(R.load_policy_source(str(tiny_run[0])), floating_base=True)


def test_bad_inputs_give_clear_errors(tiny_run, tmp_path, capsys):
    run, _ = tiny_run
    with pytest.raises(R.EvaluationError, match="no run or export directory"):
        R.load_policy_source(str(tmp_path / "missing"))
    only_config = tmp_path / "only_config"
    only_config.mkdir()
    (only_config / "config.json").write_text((run / "config.json").read_text())
    with pytest.raises(R.EvaluationError, match="params.msgpack missing"):
        R.load_policy_source(str(only_config))
    (only_config / "params.msgpack").write_bytes(b"\xc1 not msgpack")
    with pytest.raises(R.EvaluationError, match="corrupt file .*params.msgpack"):
        R.load_policy_source(str(only_config))
    other = tmp_path / "other"
    _write_run(other, layers=(4,))
    (other / "config.json").write_text((run / "config.json").read_text())  # layers (16,) vs params of (4,)
    with pytest.raises(R.EvaluationError, match="does not fit"):
        R.load_policy_source(str(other))
    (other / "config.json").write_text('{"robot": "iiwa", "bogus": 1}')
    with pytest.raises(R.EvaluationError, match="corrupt run config"):
        R.load_policy_source(str(other))
    bad_paths = tmp_path / "six_joints.csv"
    bad_paths.write_text("a,b,c,d,e,f\n" + "\n".join(",".join([str(0.1 * i)] * 6) for i in range(3)) + "\n")
    with pytest.raises(DatasetError, match="6 joint values"):
        R.user_paths(str(bad_paths), "iiwa")
    spec = importlib.util.spec_from_file_location("evaluate_cli", REPO / "evaluate.py")
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    assert cli.main([str(tmp_path / "missing")]) == 2
    assert cli.main([str(run), "--paths", str(bad_paths)]) == 2
    assert cli.main([str(run), "--terminate-deviation", "-1"]) == 2
    assert cli.main([str(run), "--end-tolerance", "nan"]) == 2
    err = capsys.readouterr().err
    assert "--end-tolerance must be a finite number >= 0" in err
    assert "no run or export directory" in err and "6 joint values" in err
    assert "--terminate-deviation must be a number > 0 (inf: no limit)" in err


@pytest.mark.parametrize("options, message", [
    (["--episodes", "-3"], "--episodes must be >= 1, got -3"),
    (["--batch", "0"], "--batch must be >= 1"),
    (["--plot-episode", "-1"], "--plot-episode must be >= 0"),
    (["--timing-decisions", "-5"], "--timing-decisions must be >= 0"),
    (["--workers", "0"], "--workers must be >= 1"),
    (["--end-knot-tolerance", "0"], "--end-knot-tolerance must be a finite number > 0"),
    (["--terminate-deviation", "nan"], "--terminate-deviation must be a number > 0 (inf: no limit), got nan"),
    (["--keep-knots"], "--keep-knots applies to --paths only"),
    (["--checkpoint", "last"], "--checkpoint must be 'latest' or a step"),
    (["--video", "clip.avi"], "--video clip.avi: the file name must end in .mp4, .gif or .png"),
    (["--video-episodes", "1"], "--video-episodes applies to --video only"),
    (["--video", "--episodes", "3", "--video-episodes", "3"], "only episodes of the first batch can be rendered (0..2)"),
    (["--video", "--video-size", "640"], "--video-size must be WxH with 16..4096 pixels per side, got '640'"),
    (["--video", "--video-fps", "0"], "--video-fps must be 1..240, got 0"),
])
def test_evaluate_option_errors_are_one_line_before_anything_loads(tmp_path, options, message):
    """Every option error of evaluate.py: one line naming the option, exit status 2, before JAX
    or the policy is loaded (the run directory here holds nothing a policy could load from)."""
    code = ("import sys, evaluate\n"
            f"rc = evaluate.main([{str(tmp_path)!r}, *{options!r}])\n"
            "print('rc', rc, 'jax imported', 'jax' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert "rc 2 jax imported False" in result.stdout, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("evaluate.py: error: ") and message in lines[0], result.stderr


def test_evaluate_accepts_no_deviation_limit():
    """``--terminate-deviation inf`` (documented: evaluate without the deviation limit, e.g. whether a
    fall follows a deviation) passes the option checks; 0 and nan do not."""
    spec = importlib.util.spec_from_file_location("evaluate_cli", REPO / "evaluate.py")
    evaluate = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(evaluate)

    assert evaluate.option_problem(evaluate.parse_args([str(REPO), "--terminate-deviation", "inf"])) is None
    for bad in ("0", "nan", "-0.1"):
        problem = evaluate.option_problem(evaluate.parse_args([str(REPO), "--terminate-deviation", bad]))
        assert problem is not None and problem.startswith("--terminate-deviation must be a number > 0"), problem


@pytest.mark.slow
def test_user_paths_are_reknotted_and_measured_against_the_users_curve(tiny_run, tmp_path, capsys):
    """evaluate.py --paths: planner-dense waypoints of two committed test paths are re-knotted by
    the run's knot rule (its dataset's), and the deviations are measured against the user's curve:
    with the knots kept, the user's curve is the reference itself and both measures agree; re-knotted,
    they differ by no more than the curves' reported distance (plus float32 arc rounding)."""
    from mjx_pathtrack.core.spline_fit import fit_spline
    from mjx_pathtrack.paths import datasets

    run, _ = tiny_run
    native = [k[:50] for k in datasets.load_split("iiwa", "random", "test")[:2]]   # ~7 rad each
    dense = {}
    for i, k in enumerate(native):
        fit = fit_spline(k)
        dense[f"p{i}"] = fit.point_at(np.append(np.arange(0.0, fit.length, 0.03), fit.length))
    file = tmp_path / "dense.npz"
    np.savez(file, **dense)
    source = R.load_policy_source(str(run))
    rule = source.training_knot_rule()
    assert rule.curvature_distance == 0.3 and rule.max_spacing == pytest.approx(
        datasets.read_config("iiwa", "random")["max_dis_between_knots"])
    user = R.load_user_paths(str(file), "iiwa", rule)
    for p, k in zip(user.prepared, native):
        assert abs(len(p.knots) - len(k)) <= 0.06 * len(k) and len(p.given) > 4 * len(k)
        assert 0 < p.joint_distance < 0.05 and 0 < p.cartesian_distance < 0.05
    assert any("re-knotted by the policy's knot rule" in line for line in user.report_lines())
    env, robot, label = R.build_env(source, user, full_paths=True)
    assert label == "dense.npz" and env.knot_rule == rule
    kw = dict(episodes=2, timing_decisions=0, topp=False)
    ours, _, _ = R.run_evaluation(env, source.policy, robot, **kw, measure=user.curves)
    theirs, _, _ = R.run_evaluation(env, source.policy, robot, **kw)
    gap = max(p.joint_distance for p in user.prepared)
    assert abs(ours["joint_dev_mean"] - theirs["joint_dev_mean"]) <= gap + 1e-3
    kept = R.load_user_paths(str(file), "iiwa", None, cartesian=False)
    env_kept, _, _ = R.build_env(source, kept, full_paths=True)
    a, _, _ = R.run_evaluation(env_kept, source.policy, robot, **kw, measure=kept.curves)
    b, _, _ = R.run_evaluation(env_kept, source.policy, robot, **kw)
    for key in ("joint_dev_mean", "joint_dev_max", "joint_dev_final", "cart_contour_dev_cm_mean"):
        assert a[key] == pytest.approx(b[key], abs=2e-4), key
    spec = importlib.util.spec_from_file_location("evaluate_cli", REPO / "evaluate.py")
    cli = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cli)
    assert cli.main([str(run), "--keep-knots"]) == 2
    assert "--keep-knots applies to --paths only" in capsys.readouterr().err
