"""Evaluate a trained policy (run directory or export) on test paths: the paper 000 §IV report.

``python evaluate.py RUN_DIR_OR_EXPORT`` is the front end. Steps: :func:`load_policy_source`
(run dir: ``config.json`` + ``params.msgpack`` through the Brax networks of
:func:`~mjx_pathtrack.deploy.networks.networks`; export dir: :func:`~mjx_pathtrack.deploy.export.load_policy`),
:func:`build_env` (dataset split or user path file, every path once by default, sub-paths from a
fixed seed), :func:`run_evaluation` (batched rollout, metrics, TOPP-RA baseline, computation time),
:func:`write_outputs` (``metrics.json``, ``episodes.csv``, plots; all written atomically).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from pathlib import Path as FsPath
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.evaluation import baseline
from mjx_pathtrack.paths import datasets, ik
from mjx_pathtrack.paths import user_paths as UP
from mjx_pathtrack.robots import registry as robots
from mjx_pathtrack.evaluation import rollout as E
from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs import registry
from mjx_pathtrack.envs.tracking import PathTrackingEnv
from mjx_pathtrack.fileio import atomic_write_bytes, json_safe
from mjx_pathtrack.config import stored
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.deploy.networks import params_observation_size, policy_networks

#: paper 000 Table VI, policy / TOPP-RA duration, iiwa random paths
PAPER_RATIO = {"iiwa": 1.27}


class EvaluationError(ValueError):
    """A missing or unusable run, checkpoint or path file; the message says which."""


@dataclasses.dataclass
class PolicySource:
    """A loaded policy: ``policy(obs [B, obs_size], key) -> action [B, n]`` (pure JAX), the
    training config (a default one rebuilt from the manifest for an export), the training
    dataset's ``max_dis_between_knots`` (observation scale) and a description."""

    policy: E.Policy
    config: TrainConfig
    max_dis: float | None
    kind: str
    path: FsPath
    knot_rule: KnotRule | None = None   # an export's (its manifest); None: the training dataset's
    observation_size: int | None = None  # what the policy reads (manifest / parameters)

    def training_knot_rule(self) -> KnotRule:
        """Where the policy's training paths have their knots: the export's record, else the
        training dataset's (``config.json``), else the papers' curvature rule at ``max_dis``."""
        if self.knot_rule is not None:
            return self.knot_rule
        cfg = self.config
        try:
            return KnotRule.of_dataset(datasets.read_config(cfg.robot, cfg.dataset, cfg.dataset_root))
        except datasets.DatasetError:
            if self.max_dis is None:
                raise
            return KnotRule(max_spacing=self.max_dis)


@dataclasses.dataclass
class UserPaths:
    """A user path file made ready for a policy (:mod:`mjx_pathtrack.paths.user_paths`): each
    path checked, moved inside the limits and re-knotted by the policy's knot rule (``rule``;
    None: knots kept as given). ``paths``: the stacked references the policy tracks; ``curves``:
    the user's own curves (what the deviations are measured against); ``label``: the file name."""

    prepared: list
    rule: KnotRule | None
    paths: S.Path
    curves: list
    label: str

    def report_lines(self) -> list[str]:
        return UP.report_lines(self.prepared, self.rule)


def load_policy_source(path: str, deterministic: bool = True, checkpoint: str | None = None,
                       allow_pickle: bool = False) -> PolicySource:
    """Load a run directory (``config.json`` + ``params.msgpack``) or an export directory
    (``manifest.json`` + ``policy.jaxexport``); :class:`EvaluationError` if unusable.
    ``deterministic=False``: the policy samples its actions from the trained Gaussian, with the
    key of each step, as during training (run directories only: an export holds the mean).
    ``checkpoint``: ``"latest"`` or a step: the policy of that checkpoint of a run directory
    (``checkpoints/``; a run still training or cut off) instead of its final parameters.
    Everything is read as data (:mod:`mjx_pathtrack.config.stored`); an older run's pickles
    (``params.pkl``, pickled checkpoints) only with ``allow_pickle``."""
    from mjx_pathtrack.deploy import export

    root = FsPath(path)
    if not root.is_dir():
        raise EvaluationError(f"no run or export directory at {root}")
    if checkpoint is not None and (root / export.MANIFEST_FILE).is_file():
        raise EvaluationError(f"{root} is an export; --checkpoint needs the run directory (its checkpoints/)")
    if (root / export.MANIFEST_FILE).is_file():
        if not deterministic:
            raise EvaluationError(f"{root} is an export, which holds only the deterministic policy; "
                                  f"sampled actions need the run directory (config.json + params.msgpack)")
        try:
            exported = export.load_policy(root)
        except export.ExportError as e:
            raise EvaluationError(str(e)) from e
        man = exported.manifest
        if "run_config" in man:  # the training run's whole configuration (the task's included)
            try:
                config = TrainConfig.from_json(json.dumps(man["run_config"]))
            except (ValueError, TypeError) as e:
                raise EvaluationError(f"{root}: corrupt run_config in the manifest: {e}") from e
        elif man.get("task", "tracking") != "tracking":
            raise EvaluationError(f"{root}: an export of the {man['task']!r} task written before exports recorded "
                                  f"the run configuration; evaluate the run directory (the export's parent) instead")
        else:
            config = TrainConfig.from_flat({"robot": man["robot"], "dt": float(man["dt"]), "n_next": int(man["n_next"]),
                                            **export.env_settings(man)})
        try:
            rule = export.manifest_knot_rule(man)
        except export.ExportError as e:
            raise EvaluationError(f"{root}: {e}") from e
        return PolicySource(lambda obs, key: exported.traced_call(obs), config, float(man["max_dis_between_knots"]),
                            "export", root, rule, exported.observation_size)
    config_file = root / "config.json"
    if not config_file.is_file():
        raise EvaluationError(f"{root} is neither a run directory (config.json missing) nor an export "
                              f"(manifest.json missing)")
    try:
        config = TrainConfig.from_json(config_file.read_text())
    except (ValueError, TypeError) as e:
        raise EvaluationError(f"corrupt run config {config_file}: {e}") from e
    if checkpoint is not None:
        params, params_file = _checkpoint_params(root, checkpoint, allow_pickle)
        policy, obs_size = _brax_policy(config, params, params_file, deterministic)
        return PolicySource(policy, config, None, "run", root, observation_size=obs_size)
    try:
        params, params_file = stored.read_params(root, allow_pickle)
    except FileNotFoundError:
        raise EvaluationError(f"{root}: {stored.PARAMS_FILE} missing (training not finished? evaluate a checkpoint "
                              f"with --checkpoint latest, or finish the run with train.py --resume)") from None
    except stored.StoredDataError as e:
        raise EvaluationError(str(e)) from e
    policy, obs_size = _brax_policy(config, params, params_file, deterministic)
    return PolicySource(policy, config, None, "run", root, observation_size=obs_size)


def _checkpoint_params(root: FsPath, which: str, allow_pickle: bool = False) -> tuple[tuple, FsPath]:
    """``((normalizer, policy, value), file)`` of checkpoint ``which`` ("latest" or a step) of run ``root``."""
    from mjx_pathtrack.config import run_dir as C

    folder = root / "checkpoints"
    if which == "latest":
        found = C.latest_checkpoint(folder)
        if found is None:
            raise EvaluationError(f"{root}: no checkpoint in {folder}")
        path = found[0]
    else:
        try:
            step = int(which)
        except ValueError:
            raise EvaluationError(f"--checkpoint must be 'latest' or a step, got {which!r}") from None
        path = C.checkpoint_path(folder, step)
        if not path.is_file():
            raise EvaluationError(f"{root}: no checkpoint of step {step} (there are: "
                                  f"{C.checkpoint_steps(folder) or 'none'})")
    try:
        data = C.load_checkpoint(path, allow_pickle)
    except C.RunDirError as e:
        raise EvaluationError(str(e)) from e
    return data["params"], path


def _brax_policy(config: TrainConfig, params, params_file: FsPath, deterministic: bool = True
                 ) -> tuple[E.Policy, int]:
    """The policy of trained ``params`` on the networks of ``config`` and the observation size
    it reads (from the parameters; :func:`build_env` checks it against the environment)."""
    from brax.training.agents.ppo import networks as ppo_nets

    try:
        obs_size = params_observation_size(params)
    except ValueError as e:
        raise EvaluationError(f"checkpoint {params_file}: {e}") from e
    if config.task == "balance":
        from mjx_pathtrack.envs.tasks import humanoid_balance

        n = len(humanoid_balance.eval_robot(config).joint_names)
    else:
        n = robots.load_robot(config.robot, dt=config.env.dt).n_joints
    nets = policy_networks(config, obs_size, n)
    policy = E.brax_policy(ppo_nets.make_inference_fn(nets), params, deterministic)
    try:
        out = jax.eval_shape(policy, jax.ShapeDtypeStruct((1, obs_size), jnp.float32), jax.random.PRNGKey(0))
    except Exception as e:
        raise EvaluationError(f"checkpoint {params_file} does not fit the networks of config.json "
                              f"(policy layers {config.network.policy_layers}, observation size {obs_size}): "
                              f"{type(e).__name__}: {e}") from e
    if out.shape != (1, n):
        raise EvaluationError(f"checkpoint {params_file}: policy output {out.shape}, expected (1, {n})")
    return policy, obs_size


def user_paths(file: str, robot: str, rule: KnotRule | None = None) -> S.Path:
    """Stacked paths of a user path file (``.npz``/``.json``/``.csv``, the datasets import format),
    checked against the robot's path joints and moved inside its limits, re-knotted by ``rule``
    (None: as given) (:class:`~mjx_pathtrack.paths.datasets.DatasetError` names a bad path)."""
    return load_user_paths(file, robot, rule, cartesian=False).paths


def load_user_paths(file: str, robot: str, rule: KnotRule | None, cartesian: bool = True) -> UserPaths:
    """:class:`UserPaths` of a path file for a registry ``robot``: every path checked (knots up to
    the URDF limits accepted and moved onto the model's), re-knotted by ``rule`` (None: kept as
    given) and the largest distance between the user's curve and the policy's measured, with
    ``cartesian`` also between the target points' curves."""
    limits, names = datasets.robot_limits(robot)
    fk = None
    if cartesian:
        loaded = robots.load_robot(robot)
        pj = np.flatnonzero(np.asarray(loaded.path_mask))
        home = np.asarray(loaded.q0, np.float64)

        def target_points(q, chunk=4096):   # fixed-size calls: one compilation for every path
            full = np.broadcast_to(home, q.shape[:-1] + home.shape).copy()
            full[..., pj] = q
            parts = []
            for i in range(0, len(full), chunk):
                part = full[i:i + chunk]
                padded = np.concatenate([part, np.repeat(part[-1:], chunk - len(part), 0)])
                parts.append(ik.target_positions(loaded, padded)[:len(part)])
            return np.concatenate(parts)
        fk = target_points
    prepared = UP.prepare_paths(datasets.read_user_paths(file), limits, rule, names,
                                allowance=robots.POS_BUFFER, fk=fk, prefix=f"{FsPath(file).name}: ")
    paths = S.stack_fits(S.fit_spline(p.knots) for p in prepared)
    return UserPaths(prepared, rule, paths, [S.fit_spline(p.given) for p in prepared], FsPath(file).name)


def check_level_plate(user: UserPaths, dt: float = 0.1) -> None:
    """Every path the ball policy would track (re-knotted) keeps the plate level
    (:func:`~mjx_pathtrack.paths.ball.check_level`; a :class:`~mjx_pathtrack.paths.datasets.DatasetError`
    names path, knot and tilt)."""
    from mjx_pathtrack.paths.ball import PlateKinematics, check_level

    kin = PlateKinematics(robots.load_robot("iiwa_ball", dt=dt))
    for p in user.prepared:
        check_level(kin, p.knots, name=p.name)


def build_env(source: PolicySource, paths_file: "str | UserPaths | None" = None, split: str = "test",
              full_paths: bool = False, floating_base: bool = False) -> tuple[PathTrackingEnv, robots.Robot, str]:
    """:func:`_build_env`, checked: the environment's observation is the size the policy reads
    (:class:`EvaluationError` naming both otherwise)."""
    env, robot, label = _build_env(source, paths_file, split, full_paths, floating_base)
    if source.observation_size is not None and env.observation_size != source.observation_size:
        raise EvaluationError(f"{source.path}: the policy reads observations of {source.observation_size} values, "
                              f"the evaluation environment of its config.json builds {env.observation_size}")
    return env, robot, label


def _build_env(source: PolicySource, paths_file: "str | UserPaths | None" = None, split: str = "test",
               full_paths: bool = False, floating_base: bool = False) -> tuple[PathTrackingEnv, robots.Robot, str]:
    """The evaluation environment: the training config's (termination, weights, executor), the
    training dataset's observation scale, on ``split`` of the training dataset or on user paths
    (``paths_file``: a file, re-knotted by the policy's rule, or :func:`load_user_paths`' result);
    ``full_paths`` evaluates whole paths instead of random sub-paths;
    ``floating_base``: a plain ARMAR-4 tracking run standing on the floor, legs fixed, MJX physics
    (:func:`~mjx_pathtrack.envs.tasks.humanoid_balance.floating_base_config`)."""
    cfg = source.config
    if floating_base:
        from mjx_pathtrack.envs.tasks import humanoid_balance

        try:
            cfg = humanoid_balance.floating_base_config(cfg)
        except ValueError as e:
            raise EvaluationError(f"--floating-base: {e}") from e
    robot = robots.load_robot(cfg.robot, dt=cfg.env.dt)
    if paths_file is not None and not isinstance(paths_file, UserPaths):
        paths_file = load_user_paths(paths_file, cfg.robot, source.training_knot_rule(), cartesian=False)
    if cfg.task == "ball_on_plate":  # whole paths, ball always simulated; episodes end when it falls
        from mjx_pathtrack.envs.tasks.ball_on_plate import make_task_env

        if paths_file is None:
            return make_task_env(cfg, split, evaluation=True), robot, f"{cfg.robot}/{cfg.dataset}/{split}"
        check_level_plate(paths_file, cfg.env.dt)
        return make_task_env(cfg, split, evaluation=True, paths=paths_file.paths), robot, paths_file.label
    max_dis = source.max_dis
    if max_dis is None:
        max_dis = float(datasets.read_config(cfg.robot, cfg.dataset, cfg.dataset_root)["max_dis_between_knots"])
    if paths_file is not None:
        paths, label = paths_file.paths, paths_file.label
    else:
        paths, label = datasets.load_paths(cfg.robot, cfg.dataset, split, root=cfg.dataset_root), \
            f"{cfg.robot}/{cfg.dataset}/{split}"
    env_cfg = cfg.env_config()
    if full_paths:
        env_cfg = dataclasses.replace(env_cfg, start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0)
    if cfg.task == "balance":
        from mjx_pathtrack.envs.tasks import humanoid_balance

        env = humanoid_balance.make_env(cfg, split, paths=paths, max_dis=max_dis, env_config=env_cfg,
                                        base_sensor=not floating_base)
        return env, humanoid_balance.eval_robot(cfg), label
    return registry.tracking_env(robot, paths, max_dis, env_cfg, cfg.executor, source.training_knot_rule()), \
        robot, label


def run_evaluation(env: PathTrackingEnv, policy: E.Policy, robot=None, episodes: int | None = None, seed: int = 0,
                   batch: int = 256, timing_decisions: int = 200, topp: bool = True, topp3: bool = False,
                   topp3_cache=None, workers: int = 2, measure: list | None = None) -> tuple[dict, dict, E.Rollout]:
    """Evaluate: ``episodes`` (default: one per path) on paths ``i mod n_paths`` in batches of
    ``batch`` (the last padded, so one compile), sub-paths from ``PRNGKey(seed)``. ``topp``: the
    TOPP-RA baseline; ``topp3``: also the jerk-limited optimum (TOPP3, ~1 s per path on
    ``workers`` processes, reused from the JSON file ``topp3_cache``); ``measure``: per dataset
    path the curve the deviations are measured against (:attr:`UserPaths.curves`; default the
    environment's references). Returns ``(summary,
    per-episode table, rollout of the first batch)``."""
    n = env.n_paths if episodes is None else int(episodes)
    if n < 1:
        raise EvaluationError(f"--episodes must be >= 1, got {n}")
    indices = np.arange(n) % env.n_paths
    size = min(batch, n)
    key = jax.random.PRNGKey(seed)
    tables, first = [], None
    for i, start in enumerate(range(0, n, size)):
        chunk = indices[start:start + size]
        padded = np.concatenate([chunk, np.repeat(chunk[-1:], size - len(chunk))])
        ro = E.rollout(env, policy, jax.random.fold_in(key, i), padded)
        table = {k: v[:len(chunk)] for k, v in E.episode_table(env, ro, robot, measure=measure).items()}
        if topp:
            paths = jax.tree.map(lambda x: x[:len(chunk)], ro.paths)
            table.update(baseline.toppra_columns(env, paths, ro.s_start[:len(chunk)], table["stop_time_s"]))
        if topp3:
            pj = np.asarray(env.path_joints)
            lim = env.limits
            paths = jax.tree.map(lambda x: x[:len(chunk)], ro.paths)
            table["topp3_duration_s"] = baseline.jerk_limited_durations(
                paths, ro.s_start[:len(chunk)], np.asarray(lim.vel)[pj], np.asarray(lim.acc)[pj],
                np.asarray(lim.jerk)[pj], cache=topp3_cache, workers=workers)
            table["ratio_to_topp3"] = baseline.duration_ratio(table["stop_time_s"], table["topp3_duration_s"])
        tables.append(table)
        first = ro if first is None else first
    table = {k: np.concatenate([t[k] for t in tables]) for k in tables[0]}
    summary = E.aggregate(table)
    if getattr(env, "task_failure", None):  # envs that end episodes on a task failure (``task_failed``)
        summary["task_failures"] = {f"{env.task_failure}_rate": summary["task_failed_rate"]}
    if topp:
        ratio = table["ratio_to_toppra"]
        summary["toppra_duration_s_mean"] = float(np.nanmean(table["toppra_duration_s"]))
        summary["ratio_to_toppra_mean"] = float(np.nanmean(ratio)) if np.isfinite(ratio).any() else float("nan")
        summary["ratio_to_toppra_max"] = float(np.nanmax(ratio)) if np.isfinite(ratio).any() else float("nan")
    if topp3:
        ratio = table["ratio_to_topp3"]
        summary["topp3_duration_s_mean"] = float(np.nanmean(table["topp3_duration_s"]))
        summary["topp3_failures"] = int(np.sum(~np.isfinite(table["topp3_duration_s"])))
        summary["ratio_to_topp3_mean"] = float(np.nanmean(ratio)) if np.isfinite(ratio).any() else float("nan")
        summary["ratio_to_topp3_max"] = float(np.nanmax(ratio)) if np.isfinite(ratio).any() else float("nan")
        if topp:
            summary["topp3_over_toppra_mean"] = float(np.nanmean(table["topp3_duration_s"] / table["toppra_duration_s"]))
    if timing_decisions > 0:
        times = E.decision_times(env, policy, first, timing_decisions, seed)
        summary["computation_time"] = {"decisions": int(len(times)), "dt_s": float(env.config.dt),
                                       "mean_s": float(times.mean()), "max_s": float(times.max()),
                                       "mean_over_dt": float(times.mean() / env.config.dt),
                                       "max_over_dt": float(times.max() / env.config.dt)}
    return summary, table, first


def format_report(summary: dict, title: str, robot_name: str) -> str:
    """The Table I / VI / IX style text report of :func:`run_evaluation`'s summary."""
    g = lambda k: summary.get(k, float("nan"))  # noqa: E731
    lines = [title, "=" * len(title),
             f"episodes {summary['episodes']}   end reached {100 * g('end_reached_rate'):.1f} %   "
             f"success {100 * g('success_rate'):.1f} %   progress {100 * g('progress_mean'):.1f} %",
             "terminations: " + ", ".join(f"{k} {100 * v:.1f} %" for k, v in summary["termination"].items()),
             *[f"task: balancing error {100 * v:.1f} % ({k[:-5].replace('_', ' ')} in {100 * v:.1f} % of the "
               "episodes; paper 000 Tables VII, VIII)" for k, v in summary.get("task_failures", {}).items()],
             "",
             "Table I   duration until stopped [s]     mean {:7.3f}   max {:7.3f}".format(g("stop_time_s_mean"),
                                                                                          g("stop_time_s_max")),
             "          time end reached [s]          mean {:7.3f}   max {:7.3f}".format(g("end_time_s_mean"),
                                                                                          g("end_time_s_max")),
             "          {:<28s}{:>9s} {:>9s} {:>9s} {:>9s}".format("deviation", "mean", "mean max", "max", "final")]
    for label, key in (("joint [rad]", "joint_dev"), ("Cartesian position [cm]", "cart_pos_dev_cm"),
                       ("orientation [deg]", "cart_rot_dev_deg"), ("contour (off the path) [cm]", "cart_contour_dev_cm")):
        if f"{key}_mean" in summary:
            lines.append("          {:<28s}{:9.4f} {:9.4f} {:9.4f} {:9.4f}".format(
                label, g(f"{key}_mean"), g(f"{key}_max_mean"), g(f"{key}_max"), g(f"{key}_final")))
    if "ratio_to_toppra_mean" in summary:
        paper = PAPER_RATIO.get(robot_name)
        lines += ["", "Table VI  TOPP-RA duration [s] mean {:7.3f}   ratio policy/TOPP-RA mean {:6.3f}  max {:6.3f}{}".format(
            g("toppra_duration_s_mean"), g("ratio_to_toppra_mean"), g("ratio_to_toppra_max"),
            f"   (paper: {paper})" if paper else "")]
    if "ratio_to_topp3_mean" in summary:
        lines += ["          TOPP3 (jerk-limited optimum) [s] mean {:7.3f}   ratio policy/TOPP3 mean {:6.3f}  max {:6.3f}"
                  "   TOPP3/TOPP-RA mean {:6.3f}   ({} failed)".format(
                      g("topp3_duration_s_mean"), g("ratio_to_topp3_mean"), g("ratio_to_topp3_max"),
                      g("topp3_over_toppra_mean"), summary.get("topp3_failures", 0))]
    if "computation_time" in summary:
        c = summary["computation_time"]
        lines += ["", "Table IX  computation time / dt (single env, jitted, {} decisions): mean {:.5f}  max {:.5f}  "
                  "({:.3f} / {:.3f} ms)".format(c["decisions"], c["mean_over_dt"], c["max_over_dt"],
                                               1e3 * c["mean_s"], 1e3 * c["max_s"])]
    a = summary["limit_audit"]
    lines += ["", "Limit audit (max |x| / limit over all steps and in-step extrema): pos {pos:.6f}  vel {vel:.6f}  "
              "acc {acc:.6f}  jerk {jerk:.6f}  -> {verdict}".format(**a, verdict="OK (<= 1)" if a["ok"] else "VIOLATED")]
    return "\n".join(lines)


def table_csv(table: dict[str, np.ndarray]) -> bytes:
    """The per-episode table as CSV bytes (one row per episode)."""
    buf = io.StringIO()
    writer = csv.writer(buf)
    keys = list(table)
    writer.writerow(["episode"] + keys)
    for i in range(len(table[keys[0]])):
        writer.writerow([i] + [_cell(table[k][i]) for k in keys])
    return buf.getvalue().encode()


def _cell(x) -> str:
    if isinstance(x, (bool, np.bool_)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return "" if not np.isfinite(x) else f"{float(x):.6g}"
    return str(x)


def write_outputs(out_dir: str, summary: dict, table: dict, meta: dict[str, Any], env: PathTrackingEnv,
                  ro: E.Rollout, robot, episode: int = 0) -> list[FsPath]:
    """Write ``metrics.json``, ``episodes.csv`` and the plots of ``episode`` of ``ro`` (atomic)."""
    from mjx_pathtrack.evaluation import plots as eval_plots

    out = FsPath(out_dir)
    files = [out / "metrics.json", out / "episodes.csv"]
    atomic_write_bytes(files[0], (json.dumps(json_safe({**meta, **summary}), indent=2) + "\n").encode())
    atomic_write_bytes(files[1], table_csv(table))
    files += eval_plots.plot_episode(out, env, ro, robot, episode)
    return files
