"""PPO training of the path-tracking policy: environment wiring, the training loop with its
evaluations, progress and logs, resume, and the run's results (parameters, export, report).
``train.py`` at the repository root is the command-line front end; the configuration lives in
:mod:`mjx_pathtrack.config.run`, run directories and checkpoints in :mod:`mjx_pathtrack.config.run_dir`.

The algorithm is :mod:`mjx_pathtrack.rl.ppo` (Brax's PPO pieces as a pure function of the whole
learner state): every evaluation interval ends with a checkpoint of that state, so a run killed
at any point and resumed with ``resume=True`` ends with the same parameters as an uninterrupted
one (same machine, same device count).

Multi-device: the environments are split over the local JAX devices and the iterations run
under ``jax.pmap`` with averaged gradients (data parallel, as Brax does); multi-host runs call
``jax.distributed.initialize()`` first (``--distributed`` in train.py; not tested here).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path as FsPath
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack import _jax_compat
from mjx_pathtrack.rl import ppo
from mjx_pathtrack.rl import warm_start as warm
from mjx_pathtrack.robots import registry as robots
from mjx_pathtrack.envs import registry
from mjx_pathtrack.envs.tasks import humanoid_balance
from mjx_pathtrack.envs.tracking import PathTrackingEnv
from mjx_pathtrack.deploy.export import export_policy
from mjx_pathtrack.fileio import append_csv_row, atomic_write_bytes, json_safe
from mjx_pathtrack.paths.train_data import ensure_train_paths
from mjx_pathtrack.evaluation.rollout import make_evaluator, summarize
from mjx_pathtrack.config.run import TrainConfig, differences, validate_config
from mjx_pathtrack.config.stored import LEGACY_PARAMS_FILE, PARAMS_FILE, learner_from_checkpoint, params_bytes
from mjx_pathtrack.config.run_dir import RunDirError, checkpoint_path, clear_run_dir, latest_checkpoint, learner_params, load_checkpoint, prepare_run_dir, save_checkpoint

_jax_compat.install()  # brax 0.14.2 on JAX >= 0.10 (GPU images); no-op on the pinned JAX


#: the environment of a config's task over a dataset split (:func:`mjx_pathtrack.envs.registry.make`)
make_env = registry.make


class Progress:
    """Prints env-steps/s, ETA and the latest evaluation; appends rows to ``progress.csv`` and
    writes the same scalars as TensorBoard events to ``run_dir/tensorboard``.

    Each row has ``wall_s`` (seconds of training so far: since this object was made, plus
    ``wall_offset`` for a resumed run), ``env_steps_per_s`` over the interval since the previous
    row (the first interval includes compilation) and the metrics passed in (``training/*``,
    this package's deterministic ``eval/*`` and sampled ``eval_sampled/*`` summaries)."""

    def __init__(self, run_dir: FsPath, total_steps: int, start_step: int = 0, echo: bool = True,
                 wall_offset: float = 0.0):
        from tensorboardX import SummaryWriter

        self.file = run_dir / "progress.csv"
        self.board = SummaryWriter(str(run_dir / "tensorboard"))
        self.echo = echo
        self.total = total_steps
        self.start = time.monotonic() - wall_offset
        self.last: tuple[int, float] | None = None
        self.start_step = start_step

    def wall(self) -> float:
        """Seconds of training so far (including those before a resume)."""
        return time.monotonic() - self.start

    def __call__(self, step: int, metrics: dict[str, Any]) -> None:
        step += self.start_step
        now = time.monotonic()
        rate = float("nan")
        if self.last is not None and step > self.last[0]:
            rate = (step - self.last[0]) / max(now - self.last[1], 1e-9)
        self.last = (step, now)
        eta = max(self.total - step, 0) / rate if rate == rate and rate > 0 else float("nan")
        row = {"step": step, "wall_s": now - self.start, "env_steps_per_s": rate, "eta_s": eta,
               **{k: float(np.asarray(v)) for k, v in metrics.items() if np.ndim(v) == 0}}
        append_csv_row(self.file, row)
        for key, value in row.items():
            if key != "step" and np.isfinite(value):
                self.board.add_scalar(key, value, step)
        self.board.flush()
        if self.echo:
            ret = row.get("eval/return", row.get("eval/episode_reward", float("nan")))
            line = f"step {step:>10,}  {rate:10,.0f} env-steps/s  ETA {eta / 60:6.1f} min  eval return {ret:8.2f}"
            for prefix, label in (("eval", "deterministic"), ("eval_sampled", "sampled")):
                if f"{prefix}/end_reached" in row:
                    line += (f"  {label}: end {100 * row[f'{prefix}/end_reached']:5.1f} %"
                             f" dev {row[f'{prefix}/mean_deviation']:.3f}"
                             + (f" x{row[f'{prefix}/ratio_to_toppra']:.2f}" if f"{prefix}/ratio_to_toppra" in row else ""))
            print(line, flush=True)


def truncate_progress(file: FsPath, after_step: int) -> None:
    """Drop the rows of ``progress.csv`` logged after ``after_step`` (a resumed run logs them again)."""
    import csv
    import io

    if not file.is_file():
        return
    with open(file, newline="") as f:
        reader = csv.DictReader(f)
        fields, rows = reader.fieldnames or [], [r for r in reader if float(r["step"]) <= after_step]
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=fields, restval="")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(file, text.getvalue().encode())


class TrainingDiverged(RuntimeError):
    """Training produced non-finite parameters or losses; the last good checkpoint is kept."""


# ---------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------


class _Program(NamedTuple):
    core: Any
    init: Any  # (seed) -> Learner (with a leading device axis when pmapped)
    epoch: Any  # (Learner, start, end) -> (Learner, summary); start, end: fractions of the budget
    devices: int
    iterations: int  # training iterations per evaluation interval
    epochs: int


def _program(config: TrainConfig, env: PathTrackingEnv, joint_names=None) -> _Program:
    """The compiled training program: one evaluation interval per call, over the local devices."""
    c = config
    devices = jax.local_device_count()
    processes = jax.process_count()
    if c.ppo.num_envs % (devices * processes):
        devices = 1 if c.ppo.num_envs % processes == 0 else devices
    axis = ppo.DEVICE_AXIS if devices > 1 else None
    core = ppo.build(c, env, axis_name=axis, action_names=joint_names)
    weights = ppo.reward_weights(c)
    epochs = max(c.eval.num_evals - 1, 1)
    iterations = max(int(np.ceil(c.ppo.num_timesteps / (epochs * core.steps_per_iteration))), 1)
    envs_per_device = c.ppo.num_envs // (devices * processes)

    def step(learner, fraction):
        return ppo.scheduled_iteration(core, weights, learner, fraction)

    if devices == 1:
        def init(seed):
            return jax.jit(lambda: core.init(seed, weights, envs_per_device, jax.process_index()))()

        return _Program(core, init, ppo.make_epoch(jax.jit(step, donate_argnums=(0,)), iterations), 1, iterations,
                        epochs)

    first = jax.process_index() * devices

    def init(seed):
        return jax.pmap(lambda d: core.init(seed, weights, envs_per_device, d), axis_name=axis)(
            first + jnp.arange(devices))

    pmapped = jax.pmap(step, axis_name=axis, in_axes=(0, None), donate_argnums=(0,))
    return _Program(core, init, ppo.make_epoch(pmapped, iterations), devices, iterations, epochs)


def _eval_baseline(env: PathTrackingEnv, key, episodes: int) -> np.ndarray:
    """TOPP-RA durations of the evaluation episodes (the same every evaluation: a fixed key), so
    that progress.csv shows the policy/TOPP-RA ratio."""
    from mjx_pathtrack.evaluation import baseline
    from mjx_pathtrack.evaluation.rollout import episode_references

    paths, s_start = episode_references(env, key, episodes)
    pj = np.asarray(env.path_joints)
    return baseline.baseline_durations(paths, s_start, np.asarray(env.limits.vel)[pj], np.asarray(env.limits.acc)[pj])


def _host(tree):
    return jax.tree.map(np.asarray, jax.device_get(tree))


def _warm_start(config: TrainConfig, program: _Program, learner, env, joint_names, verbose: bool,
                allow_pickle: bool = False):
    """``learner`` started from ``config.init_from``'s networks (:mod:`mjx_pathtrack.rl.warm_start`);
    joints that run did not drive are fitted to hold still, unless an action prior holds them
    (``--leg-prior hold``: their zero mean head leaves them the prior's hold actions)."""
    layout = warm.PolicyLayout.of_env(env, joint_names)
    learner, new = warm.warm_start(learner, config.init_from, program.devices, layout, allow_pickle)
    prior = humanoid_balance.action_prior(config)
    held = np.intersect1d(new, prior.joints) if prior is not None else np.zeros(0, np.int64)
    new = np.setdiff1d(new, held)
    if len(held) and verbose:
        print(f"--init-from: {len(held)} joints new to the source policy "
              f"({', '.join(joint_names[i] for i in held)}) held still by the leg prior", flush=True)
    if len(new):
        learner, fit = warm.fit_new_joints(program.core.make_policy, learner, env, new, program.devices,
                                           jax.random.PRNGKey(config.seed + 2))
        if verbose:
            names = [joint_names[i] for i in new]
            print(f"--init-from: {len(names)} joints new to the source policy ({', '.join(names)}) fitted to hold "
                  f"still on {fit['states']:,} states: RMS action error new joints {fit['rms_new_before']:.3f} -> "
                  f"{fit['rms_new_after']:.3f}, the source's joints {fit['rms_old_before']:.3f} -> "
                  f"{fit['rms_old_after']:.3f}", flush=True)
    return learner


def train(config: TrainConfig, run_dir: str | os.PathLike, resume: bool = False, verbose: bool = True,
          overwrite: bool = False, allow_pickle: bool = False):
    """Train; returns ``(make_inference_fn, params, report)`` where ``report`` holds the
    evaluation summaries before and after training on the test split (deterministic policy:
    ``before``/``after``; sampled: ``before_sampled``/``after_sampled``). The run directory gets
    ``config.json``, ``progress.csv``, ``checkpoints/`` (the whole learner state after every
    evaluation interval), ``params.msgpack``, ``report.json`` and the jitted policy export
    ``export/`` (:mod:`mjx_pathtrack.deploy.export`).

    Every option is validated and the run directory checked before anything is written: a
    directory that holds a run is only continued with ``resume`` (the saved config must be
    equal) or replaced with ``overwrite``. ``resume`` continues exactly: the final parameters
    equal those of an uninterrupted run. Parameters and checkpoints are stored as data
    (:mod:`mjx_pathtrack.config.stored`); ``allow_pickle`` lets ``resume`` and ``init_from`` read
    an older run's pickles. Non-finite parameters or losses stop the run with
    :class:`TrainingDiverged`; the last good checkpoint stays."""
    run_dir = FsPath(run_dir)
    validate_config(config)
    held = prepare_run_dir(run_dir, resume, overwrite)
    config_file = run_dir / "config.json"
    if resume and config_file.exists():
        saved = TrainConfig.from_json(config_file.read_text())
        if saved != config:
            changed = differences(saved, config)
            raise ValueError(f"--resume: config differs from the saved one in {config_file} ({', '.join(changed)})")
    latest = latest_checkpoint(run_dir / "checkpoints") if resume else None
    checkpoint = load_checkpoint(latest[0], allow_pickle) if latest else None
    created = not run_dir.exists()
    try:
        if overwrite and held:
            clear_run_dir(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(config_file, config.to_json().encode())
        return _train(config, run_dir, checkpoint, verbose, allow_pickle)
    except BaseException:
        if created and latest_checkpoint(run_dir / "checkpoints") is None:
            import shutil

            shutil.rmtree(run_dir, ignore_errors=True)  # nothing trained yet: leave nothing behind
        raise


def _train(config: TrainConfig, run_dir: FsPath, checkpoint: dict | None, verbose: bool, allow_pickle: bool = False):
    root = ensure_train_paths(config.robot, config.dataset, config.num_train_paths, config.dataset_root,
                              run_dir / "data", log=print if verbose else None)
    env, test_env = make_env(config, "train", root), make_env(config, "test", root)
    joint_names = getattr(test_env, "joint_names", None) or robots.load_robot(config.robot, dt=config.env.dt).joint_names
    program = _program(config, env, joint_names)
    core = program.core
    steps_per_epoch = program.iterations * core.steps_per_iteration
    total = program.epochs * steps_per_epoch
    evaluator = make_evaluator(test_env, core.make_policy, config.eval.episodes, deterministic=None)
    eval_key = jax.random.PRNGKey(config.seed + 1)
    toppra = _eval_baseline(test_env, eval_key, config.eval.episodes)

    def evaluation(learner) -> dict[str, float]:
        params = learner_params(learner, program.devices)
        out = {}
        for sampled, prefix in ((False, "eval"), (True, "eval_sampled")):
            for k, v in summarize(evaluator(params, eval_key, sampled), toppra).items():
                out[f"{prefix}/{k}"] = v
        return out

    checkpoints = run_dir / "checkpoints"
    if checkpoint is None:
        learner, start_step, wall, evals = program.init(config.seed), 0, 0.0, {}
        if config.init_from is not None:
            learner = _warm_start(config, program, learner, env, joint_names, verbose, allow_pickle)
        truncate_progress(run_dir / "progress.csv", -1)
    else:
        if int(checkpoint["devices"]) != program.devices:
            raise RunDirError(f"{checkpoints}: written by a run on {checkpoint['devices']} devices, this one has "
                              f"{program.devices}; resume on the same number of devices")
        where = str(checkpoint_path(checkpoints, checkpoint["step"]))
        template = jax.eval_shape(lambda: program.init(config.seed))   # the structure only: nothing runs
        learner = jax.tree.map(jnp.asarray, learner_from_checkpoint(template, checkpoint, where))
        start_step, wall, evals = int(checkpoint["step"]), float(checkpoint["wall_s"]), checkpoint["evaluations"]
        truncate_progress(run_dir / "progress.csv", int(checkpoint["step"]))
        if verbose:
            print(f"resuming from {checkpoints.name}/{checkpoint_path(checkpoints, checkpoint['step']).name} "
                  f"({checkpoint['step']:,} of {total:,} steps done, {wall / 60:.1f} min)", flush=True)
    progress = Progress(run_dir, total, 0, echo=verbose, wall_offset=wall)
    if checkpoint is not None:  # the first interval's rate then includes the compilation, as in a new run
        progress.last = (int(checkpoint["step"]), time.monotonic())
    if checkpoint is None:
        evals["before"] = evaluation(learner)
        if verbose:
            print("evaluation before training:", _fmt(_unprefix(evals["before"], "eval")), flush=True)
        progress(0, evals["before"])
    latest = evals.get("latest", evals["before"])
    # intervals of steps_per_epoch until the budget is used (a resumed run whose config.json was
    # edited to a larger num_timesteps goes on with intervals of the new size)
    step = start_step
    while step < total:
        learner, summary = program.epoch(learner, np.float32(step / total), np.float32((step + steps_per_epoch) / total))
        summary = _host(summary)
        if program.devices > 1:
            summary = jax.tree.map(lambda x: x[0], summary)
        step += steps_per_epoch
        finite = bool(ppo.all_finite((learner.params, learner.normalizer_params))) and \
            all(np.isfinite(v) for v in summary.values())
        if not finite:
            last = latest_checkpoint(checkpoints)
            raise TrainingDiverged(
                f"training diverged between steps {step - steps_per_epoch:,} and {step:,}: non-finite parameters or "
                f"losses (try a lower --learning-rate); the last good checkpoint is "
                f"{last[0] if last else 'none (diverged in the first interval)'}")
        latest = evaluation(learner)
        metrics = {**{f"training/{k}": v for k, v in summary.items()}, **latest}
        progress(step, metrics)
        evals["latest"] = latest
        save_checkpoint(checkpoints, step, progress.wall(), program.devices, _host(learner), evals)
    params = learner_params(learner, program.devices)
    report = {"before": _unprefix(evals["before"], "eval"), "after": _unprefix(latest, "eval"),
              "before_sampled": _unprefix(evals["before"], "eval_sampled"),
              "after_sampled": _unprefix(latest, "eval_sampled")}
    if verbose:
        print("evaluation after training:  ", _fmt(report["after"]), flush=True)
        print("  sampled actions:          ", _fmt(report["after_sampled"]), flush=True)
    write_results(run_dir, core.make_policy, params, test_env, config, joint_names, report)
    return core.make_policy, params, report


def write_results(run_dir: FsPath, make_policy, params, env, config: TrainConfig, joint_names, report: dict) -> None:
    """``params.msgpack``, ``export/`` and ``report.json`` of a finished run, written side by side
    first and then moved into place (a kill leaves the previous set or the new one, each file
    whole; the export directory is swapped as a whole)."""
    import shutil

    staging = run_dir / ".results.tmp"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    atomic_write_bytes(staging / PARAMS_FILE, params_bytes(params))
    export_policy(staging / "export", make_policy, params, env, config.robot, joint_names, config.to_json())
    atomic_write_bytes(staging / "report.json", (json.dumps(json_safe(report), indent=2) + "\n").encode())
    old_export = run_dir / ".export.old"
    shutil.rmtree(old_export, ignore_errors=True)
    if (run_dir / "export").exists():
        os.replace(run_dir / "export", old_export)
    os.replace(staging / "export", run_dir / "export")
    os.replace(staging / PARAMS_FILE, run_dir / PARAMS_FILE)
    if (run_dir / LEGACY_PARAMS_FILE).exists():   # (an older run's pickle, replaced by the data above)
        (run_dir / LEGACY_PARAMS_FILE).unlink()
    os.replace(staging / "report.json", run_dir / "report.json")
    shutil.rmtree(old_export, ignore_errors=True)
    staging.rmdir()


def _unprefix(metrics: dict[str, float], prefix: str) -> dict[str, float]:
    return {k[len(prefix) + 1:]: v for k, v in metrics.items() if k.startswith(prefix + "/")}


def _fmt(summary: dict[str, float]) -> str:
    return "  ".join(f"{k}={v:.3f}" for k, v in summary.items())
