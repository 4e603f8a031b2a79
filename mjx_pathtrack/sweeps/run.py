"""Trade-off sweeps: train a grid of configurations, evaluate each, write ``summary.csv``.

    python train.py --sweep sweep.yaml [--out DIR]
    python -m mjx_pathtrack.sweeps.run sweep.yaml [--out DIR] [--vectorize | --sequential]

A sweep file (YAML) holds::

    base:                 # TrainConfig options (flat names or dotted paths) shared by every point
      num_timesteps: 200000
    grid:                 # option -> list of values; the points are the Cartesian product
      alpha: [1.0, 2.0]
      beta: [0.5, 0.9]
      seed: [0, 1]
    test_datasets: [target_point]   # optional: also evaluate on the test split of these datasets
    eval_episodes: 64               # episodes per evaluation (default 64)
    eval_seed: 0                    # the same episodes (paths, sub-paths) for every point
    vectorize: true                 # default: train points that differ only in alpha/beta/
                                    # action_reward/seed together in one vmapped program
                                    # (mjx_pathtrack.rl.batched_ppo); false: one Brax PPO run each
    out: runs/sweeps/my_sweep       # optional default output directory

Each point gets a run directory ``OUT/<field=value_...>`` (``config.json``, ``progress.csv``,
``params.msgpack``, ``export/`` and, written last, ``sweep_metrics.json``); ``OUT/summary.csv`` has one
row per finished point: the swept values, the run directory, the training time and the
evaluation metrics (:func:`evaluate_group`). Re-running the same command skips finished points
(a point whose ``sweep_metrics.json`` exists) and continues an interrupted sequential point from
its last Brax checkpoint.

Two trainers. *Vectorised* (default; ``benchmarks/bench_sweep.py`` measured it faster on CPU):
the points of a group (equal in every field but ``alpha``, ``beta``, ``action_reward``,
``seed``) are trained together by :mod:`mjx_pathtrack.rl.batched_ppo`, one compilation for the
group; its run directories have no Brax checkpoints, TensorBoard logs or before/after
``report.json``, and an interrupted group is trained again from the start. *Sequential*
(``vectorize: false`` / ``--sequential``): :func:`mjx_pathtrack.rl.training.train` per point, the
full run directory of ``train.py``. Both evaluate with the same code (:class:`Evaluation`).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import sys
import time
from pathlib import Path as FsPath
from typing import Any, Sequence

import numpy as np

from mjx_pathtrack.fileio import append_csv_row, atomic_write, atomic_write_bytes
from mjx_pathtrack.config.run import TrainConfig
from mjx_pathtrack.config.stored import PARAMS_FILE, params_bytes
from mjx_pathtrack.fileio import json_safe
from mjx_pathtrack.sweeps.spec import Point, SweepError, SweepSpec, _label, check_datasets, grid_points, load_spec, steps_mjx_physics

#: written last into a point's run directory: the point is finished
METRICS_FILE = "sweep_metrics.json"
#: episode 0 of the evaluation (joint trajectories for plots)
EPISODE_FILE = "episode0.npz"
SUMMARY_FILE = "summary.csv"
#: evaluation metrics (columns of summary.csv, per evaluated dataset)
METRICS = ("return", "end_reached", "success", "stop_time_s", "mean_deviation", "max_deviation",
           "terminated_deviation", "progress", "toppra_duration_s", "ratio_to_toppra")
#: limit audit columns: largest in-step |x| / limit over all evaluation steps (<= 1 + 1e-6)
AUDIT = ("max_pos_ratio", "max_vel_ratio", "max_acc_ratio", "max_jerk_ratio")


# -- sweep file --------------------------------------------------------------------------------


# -- evaluation --------------------------------------------------------------------------------

class Evaluation:
    """Evaluates trained parameters on the test split of the training dataset and of extra
    datasets: ``episodes`` episodes drawn from ``PRNGKey(seed)`` (the same paths and sub-paths for
    every point), deterministic policy, jitted once per configuration group and dataset and
    vmapped over the points of a group. Metrics: :func:`mjx_pathtrack.evaluation.rollout.summarize`
    (return, end-reached and success rates, stop time = duration [s], mean over episodes of the
    per-step mean / max deviation [rad] of the reward, deviation terminations, progress), plus
    the TOPP-RA duration of the same sub-paths (computed once per dataset) and the mean
    policy/TOPP-RA duration ratio over the episodes that stopped at the end."""

    def __init__(self, episodes: int, seed: int):
        self.episodes_n, self.seed = episodes, seed
        self._fns: dict = {}
        self._episodes: dict = {}

    def env(self, config: TrainConfig, dataset: str | None):
        from mjx_pathtrack.rl import batched_ppo
        from mjx_pathtrack.paths import datasets
        from mjx_pathtrack.envs.tracking import PathTrackingEnv
        from mjx_pathtrack.rl.training import make_env

        key = ("env", batched_ppo.shared_key(config), dataset)
        if key not in self._fns:
            env = make_env(config, "test")
            if dataset is not None and dataset != config.dataset:  # observation scale of the training set
                paths = datasets.load_paths(config.robot, dataset, "test", root=config.dataset_root)
                if config.task == "balance":   # the task's environment, not a plain tracking one
                    from mjx_pathtrack.envs.tasks import humanoid_balance

                    env = humanoid_balance.make_env(config, "test", paths=paths, max_dis=env.max_dis)
                elif config.task == "tracking":
                    env = PathTrackingEnv(env.limits, paths, env.max_dis, env.config, path_joints=env.path_joints,
                                          home=env.home, executor=env.executor)
                else:
                    raise SweepError(f"a {config.task!r} sweep is evaluated on its own dataset only, "
                                     f"not on {dataset!r}")
            self._fns[key] = env
        return self._fns[key]

    def _evaluator(self, config: TrainConfig, dataset: str | None):
        import jax
        import jax.numpy as jnp

        from mjx_pathtrack.rl import batched_ppo
        from mjx_pathtrack.evaluation import rollout as E

        key = ("fn", batched_ppo.shared_key(config), dataset)
        if key not in self._fns:
            env = self.env(config, dataset)
            make_policy = _make_policy(config, env)
            n = self.episodes_n

            @jax.jit
            def run(params, weights, rng):
                # E.evaluate's episodes (same keys), through E.run_episodes with recording on, so that
                # episode 0's trajectory and the in-step limit ratios come from the same rollout
                def one(p, w):
                    member_env = batched_ppo.with_reward_weights(env, *(w[i] for i in range(4)))
                    reset_keys = jax.random.split(rng, n + 1)
                    state = jax.vmap(member_env.reset)(reset_keys[1:])
                    steps = env.config.max_episode_steps() + 1
                    metrics, _, rec = E.run_episodes(member_env, E.brax_policy(make_policy, p), state,
                                             jax.random.split(reset_keys[0], steps), record=True)
                    first = {k: rec[k][:, 0] for k in ("executed", "p", "v", "a", "live", "limit_ratio")}
                    audit = jnp.max(jnp.where(rec["live"][..., None, None], rec["limit_ratio"], 0.0), axis=(0, 1, 3))
                    return metrics, first, audit
                return jax.vmap(one)(params, weights)

            self._fns[key] = run
        return self._fns[key]

    def episodes(self, config: TrainConfig, dataset: str | None) -> dict[str, np.ndarray]:
        """The evaluation episodes (they do not depend on the policy): TOPP-RA durations
        ``toppra [episodes]`` [s] (NaN where it fails), and episode 0's reference ``knots [K, m]``,
        ``s_start`` [rad] and dataset ``path_index``. Computed once per group and dataset."""
        import jax

        from mjx_pathtrack.evaluation import baseline
        from mjx_pathtrack.rl import batched_ppo

        key = (batched_ppo.shared_key(config), dataset)
        if key not in self._episodes:
            env = self.env(config, dataset)
            reset_keys = jax.random.split(jax.random.PRNGKey(self.seed), self.episodes_n + 1)
            track = jax.vmap(env.reset)(reset_keys[1:]).pipeline_state  # the episodes the evaluator runs
            paths = jax.tree.map(np.asarray, jax.vmap(env.episode_path)(track))
            s_start = np.asarray(track.s_start)
            pj = np.asarray(env.path_joints)
            toppra = baseline.baseline_durations(paths, s_start, np.asarray(env.limits.vel)[pj],
                                                 np.asarray(env.limits.acc)[pj])
            self._episodes[key] = {"toppra": toppra, "knots": paths.knots[0][:int(paths.n_knots[0])],
                                   "s_start": s_start[0], "path_index": np.asarray(track.path_index)[0]}
        return self._episodes[key]

    def __call__(self, configs: Sequence[TrainConfig], params: Sequence[Any], dataset: str | None = None
                 ) -> tuple[list[dict[str, float]], list[dict[str, np.ndarray]]]:
        """Metrics (:data:`METRICS` and the limit audit ``max_{pos,vel,acc,jerk}_ratio``) and the
        recorded episode 0 (:func:`episode_record`) of each point of one group (equal
        ``shared_key``)."""
        import jax
        import jax.numpy as jnp

        from mjx_pathtrack.evaluation import baseline
        from mjx_pathtrack.rl import batched_ppo
        from mjx_pathtrack.evaluation import rollout as E

        run = self._evaluator(configs[0], dataset)
        stacked = jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *params)
        weights = batched_ppo.member_weights(batched_ppo.Members.of(configs))
        metrics, first, audit = jax.tree.map(np.asarray, run(stacked, weights, jax.random.PRNGKey(self.seed)))
        info = self.episodes(configs[0], dataset)
        topp = info["toppra"]
        env = self.env(configs[0], dataset)
        rows, records = [], []
        for m in range(len(configs)):
            member = jax.tree.map(lambda x, m=m: x[m], metrics)
            row = E.summarize(member)
            ratio = baseline.duration_ratio(member.stop_time, topp)
            row["toppra_duration_s"] = float(np.nanmean(topp)) if np.isfinite(topp).any() else float("nan")
            row["ratio_to_toppra"] = float(np.nanmean(ratio)) if np.isfinite(ratio).any() else float("nan")
            row = {k: row[k] for k in METRICS}
            row.update({f"max_{q}_ratio": float(audit[m][i]) for i, q in enumerate(("pos", "vel", "acc", "jerk"))})
            rows.append(row)
            records.append(episode_record(env, {k: v[m] for k, v in first.items()}, info))
        return rows, records


def episode_record(env, rec: dict[str, np.ndarray], info: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One evaluation episode as flat arrays (saved as ``episode0.npz``): ``dt`` [s]; ``p, v, a
    [T, n]`` commanded state after each live step; ``executed [T, S+1, n]`` executed positions at
    the sub-steps; ``limit_ratio [T, 4, n]``; the joint limits; ``path_joints``; the reference
    ``knots [K, m]``, ``s_start`` and ``path_index``."""
    live = np.asarray(rec["live"], bool)
    lim = env.limits
    return {"dt": np.float64(env.config.dt), "p": rec["p"][live], "v": rec["v"][live], "a": rec["a"][live],
            "executed": rec["executed"][live], "limit_ratio": rec["limit_ratio"][live],
            "pos_min": np.asarray(lim.pos_min), "pos_max": np.asarray(lim.pos_max), "vel": np.asarray(lim.vel),
            "acc": np.asarray(lim.acc), "jerk": np.asarray(lim.jerk), "path_joints": np.asarray(env.path_joints),
            "knots": info["knots"], "s_start": np.float64(info["s_start"]), "path_index": np.int64(info["path_index"])}


def _make_policy(config: TrainConfig, env):
    from brax.training.agents.ppo import networks as brax_ppo_networks

    from mjx_pathtrack.deploy.networks import policy_networks

    return brax_ppo_networks.make_inference_fn(policy_networks(config, env.observation_size, env.action_size))


# -- running -----------------------------------------------------------------------------------

def _is_done(run_dir: FsPath, point: Point) -> bool:
    """Whether ``run_dir`` holds a finished evaluation of ``point`` (error if of another config)."""
    config_file = run_dir / "config.json"
    if config_file.is_file():
        saved = TrainConfig.from_json(config_file.read_text())
        if saved != point.config:
            raise SweepError(f"{run_dir} holds a run of another configuration (sweep file changed?); "
                             f"use another output directory or remove it")
    return (run_dir / METRICS_FILE).is_file()


def _write_json(file: FsPath, data: dict) -> None:
    atomic_write_bytes(file, (json.dumps(json_safe(data), indent=2) + "\n").encode())


def _finish_point(run_dir: FsPath, point: Point, trainer: str, train_seconds: float, metrics: dict,
                  episode: dict[str, np.ndarray]) -> dict:
    """Write ``episode0.npz`` and, last, ``sweep_metrics.json`` (the point is done); returns it."""
    atomic_write(run_dir / EPISODE_FILE, lambda f: np.savez(f, **episode))
    record = {"point": point.name, "values": {k: _jsonable(v) for k, v in point.values.items()},
              "trainer": trainer, "train_seconds": train_seconds, "metrics": metrics}
    _write_json(run_dir / METRICS_FILE, record)
    return record


def _jsonable(v):
    return list(v) if isinstance(v, tuple) else v


def evaluate_group(points: Sequence[Point], params: Sequence[Any], evaluation: Evaluation,
                   spec: SweepSpec) -> tuple[list[dict[str, float]], list[dict[str, np.ndarray]]]:
    """Metrics of each point on the training dataset's test split (plain names) and on each extra
    test dataset (``on_<dataset>_<metric>``), and episode 0 on the training dataset's test split."""
    configs = [p.config for p in points]
    rows, episodes = evaluation(configs, params)
    for name in spec.test_datasets:
        if name == configs[0].dataset:
            continue
        for row, extra in zip(rows, evaluation(configs, params, name)[0]):
            row.update({f"on_{name}_{k}": v for k, v in extra.items() if k in METRICS})
    return rows, episodes


def _train_sequential(point: Point, run_dir: FsPath, verbose: bool):
    from mjx_pathtrack.rl.training import train

    t0 = time.monotonic()
    try:
        _, params, _ = train(point.config, run_dir, resume=True, verbose=verbose)
    except ValueError as e:
        raise SweepError(f"point {point.name}: {e}") from e
    return jax_to_numpy(params), time.monotonic() - t0


def jax_to_numpy(tree):
    import jax

    return jax.tree.map(np.asarray, tree)


def _train_vectorized(points: Sequence[Point], out: FsPath, verbose: bool):
    """Train ``points`` (one group) together; write each run directory's config, progress,
    params and export. Returns ``(params_list, seconds per point)``."""
    from mjx_pathtrack.rl import batched_ppo
    from mjx_pathtrack.robots import registry as robots
    from mjx_pathtrack.deploy.export import export_policy
    from mjx_pathtrack.rl.training import make_env

    configs = [p.config for p in points]
    dirs = [out / p.name for p in points]
    for d, c in zip(dirs, configs):
        d.mkdir(parents=True, exist_ok=True)
        _write_json(d / "config.json", dataclasses.asdict(c))
        (d / "progress.csv").unlink(missing_ok=True)
    t0 = time.monotonic()
    last = [t0, 0]

    def progress(step, rows):
        now = time.monotonic()
        rate = (step - last[1]) * len(rows) / max(now - last[0], 1e-9)
        last[:] = [now, step]
        for d, row in zip(dirs, rows):
            append_csv_row(d / "progress.csv", {"step": step, "env_steps_per_s_all_points": rate, **row})
        if verbose:
            print(f"  vmapped x{len(rows)}: step {step:>10,}  {rate:10,.0f} env-steps/s (all points)  returns "
                  + " ".join(f"{r['episode_return']:.1f}" for r in rows), flush=True)

    make_policy, params, seconds = batched_ppo.train_members(configs, progress=progress)
    t0 = time.monotonic()
    test_env = make_env(configs[0], "test")
    joint_names = robots.load_robot(configs[0].robot, dt=configs[0].env.dt).joint_names
    for d, c, p in zip(dirs, configs, params):
        atomic_write_bytes(d / PARAMS_FILE, params_bytes(p))
        export_policy(d / "export", make_policy, p, test_env, c.robot, joint_names, c.to_json())
    if verbose:
        print(f"  exported {len(points)} policies in {time.monotonic() - t0:.1f} s", flush=True)
    return params, seconds / len(points)


def write_summary(out: FsPath, spec: SweepSpec, points: Sequence[Point]) -> FsPath:
    """(Re)write ``out/summary.csv`` (atomically) from the finished points' ``sweep_metrics.json``."""
    rows = []
    for p in points:
        file = out / p.name / METRICS_FILE
        if file.is_file():
            rec = json.loads(file.read_text())
            rows.append({"point": p.name, **{k: _label(v) if isinstance(v, tuple) else v for k, v in p.values.items()},
                         "run_dir": p.name, "trainer": rec["trainer"], "train_seconds": rec["train_seconds"],
                         **rec["metrics"]})
    columns = ["point", *spec.grid, "run_dir", "trainer", "train_seconds", *METRICS, *AUDIT]
    for name in spec.test_datasets:
        columns += [f"on_{name}_{k}" for k in METRICS]
    columns = [c for c in dict.fromkeys(columns) if any(c in r for r in rows)] if rows else columns
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if v is None or (isinstance(v, float) and not np.isfinite(v)) else v)
                         for k, v in r.items()})
    file = out / SUMMARY_FILE
    atomic_write_bytes(file, buf.getvalue().encode())
    return file


def groups(points: Sequence[Point]) -> list[list[Point]]:
    """Points grouped by everything but the member fields (alpha, beta, action_reward, seed)."""
    from mjx_pathtrack.rl import batched_ppo

    out: dict = {}
    for p in points:
        out.setdefault(batched_ppo.shared_key(p.config), []).append(p)
    return list(out.values())


def run_sweep(spec: SweepSpec, out: str | FsPath, vectorize: bool | None = None, verbose: bool = True) -> FsPath:
    """Train and evaluate every unfinished point of ``spec`` under ``out``; returns the path of
    ``summary.csv``. ``vectorize`` overrides the file's setting."""
    out = FsPath(out)
    points = grid_points(spec)
    check_datasets(spec, points)
    vectorize = spec.vectorize if vectorize is None else vectorize
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out / "sweep.json", (json.dumps(
        {"base": {k: _jsonable(v) for k, v in spec.base.items()},
         "grid": {k: [_jsonable(v) for v in vs] for k, vs in spec.grid.items()},
         "test_datasets": list(spec.test_datasets), "eval_episodes": spec.eval_episodes,
         "eval_seed": spec.eval_seed}, indent=2) + "\n").encode())
    evaluation = Evaluation(spec.eval_episodes, spec.eval_seed)
    todo = [p for p in points if not _is_done(out / p.name, p)]
    if verbose:
        print(f"sweep: {len(points)} points, {len(points) - len(todo)} already done, output {out}", flush=True)
    write_summary(out, spec, points)
    for group in groups(todo):
        if vectorize and len(group) > 1:
            if verbose:
                print(f"training {len(group)} points together: {', '.join(p.name for p in group)}", flush=True)
            params, seconds = _train_vectorized(group, out, verbose)
            t0 = time.monotonic()
            metrics, episodes = evaluate_group(group, params, evaluation, spec)
            if verbose:
                print(f"  trained in {seconds * len(group):.1f} s, evaluated in {time.monotonic() - t0:.1f} s",
                      flush=True)
            for p, m, e in zip(group, metrics, episodes):
                _finish_point(out / p.name, p, "vmapped", seconds, m, e)
            write_summary(out, spec, points)
            continue
        for p in group:
            if verbose:
                print(f"training point {p.name}", flush=True)
            params, seconds = _train_sequential(p, out / p.name, verbose)
            t0 = time.monotonic()
            metrics, episodes = evaluate_group([p], [params], evaluation, spec)
            if verbose:
                print(f"  trained in {seconds:.1f} s, evaluated in {time.monotonic() - t0:.1f} s", flush=True)
            _finish_point(out / p.name, p, "brax", seconds, metrics[0], episodes[0])
            write_summary(out, spec, points)
    return write_summary(out, spec, points)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep", help="sweep file (YAML)")
    parser.add_argument("--out", default=None, help="output directory (default: the file's 'out' or runs/sweeps/<name>)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--vectorize", dest="vectorize", action="store_true", default=None,
                      help="train points differing only in alpha/beta/action_reward/seed in one vmapped program")
    mode.add_argument("--sequential", dest="vectorize", action="store_false", help="one Brax PPO run per point")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        spec = load_spec(args.sweep)
        out = args.out or spec.out or f"runs/sweeps/{FsPath(args.sweep).stem}"
        summary = run_sweep(spec, out, args.vectorize, verbose=not args.quiet)
    except SweepError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"summary: {summary}")
    print(summary.read_text())
    return 0


if __name__ == "__main__":
    import mjx_pathtrack

    # before JAX starts (python -m mjx_pathtrack.sweeps.run FILE ...)
    mjx_pathtrack.prepare_xla(mjx_physics=len(sys.argv) < 2 or steps_mjx_physics(sys.argv[1]))
    sys.exit(main())
