"""Export a trained policy as a serialized jitted function, and load it without the training stack.

An export directory holds ``policy.jaxexport`` -- the deterministic policy (observation
normalisation, network, tanh mean) serialized with ``jax.export`` for any batch size --,
``policy.onnx`` -- the same function as an ONNX graph, checked against it
(:mod:`~mjx_pathtrack.deploy.onnx_policy`) -- and ``manifest.json`` (robot, joint names, limits,
Δt, N knots, observation layout, shapes, package and JAX versions). :func:`load_policy` needs only
``jax`` and ``numpy``: no Brax, no Flax, no training code; the ONNX file needs only
``onnxruntime``. Files are written atomically.
"""

from __future__ import annotations

import json
import math
import os
import sys
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.deploy.onnx_policy import ONNX_FILE, observation_batch
from mjx_pathtrack.fileio import atomic_write_bytes

FORMAT_VERSION = 1
POLICY_FILE = "policy.jaxexport"
MANIFEST_FILE = "manifest.json"


#: manifest keys that loading and the controller rely on, with their JSON types
_NUMBER = (int, float)
REQUIRED_KEYS = {"robot": (str, "a string"), "joint_names": (list, "a list"), "path_joints": (list, "a list"),
                 "dt": (_NUMBER, "a number"), "n_next": (int, "an integer"), "max_dis_between_knots": (_NUMBER, "a number"),
                 "limits": (dict, "an object"), "observation_size": (int, "an integer"), "action_size": (int, "an integer")}


#: the environment settings (``EnvConfig`` fields) a manifest records, each with the value that a
#: manifest written before the setting existed implies (None: the setting's default)
MANIFEST_ENV_SETTINGS = {"knots_frame": "absolute", "end_braking": "at_end", "end_stop": "fastest",
                         "end_knot_tolerance": None, "observe_deviation": False,
                         "observe_speed_limits": False}


class ExportError(ValueError):
    """A missing, corrupt or incompatible export; the message says which."""


def env_settings(manifest: dict) -> dict:
    """The environment settings of an export's ``manifest`` (:data:`MANIFEST_ENV_SETTINGS`), older
    manifests' missing ones filled in; a setting left at its default is left out."""
    settings = {key: manifest.get(key, implied) for key, implied in MANIFEST_ENV_SETTINGS.items()}
    return {key: value for key, value in settings.items() if value is not None}


def manifest_knot_rule(manifest: dict) -> KnotRule:
    """The knot rule of the export's training paths (:class:`~mjx_pathtrack.core.knot_rule.KnotRule`):
    the manifest's ``knot_rule``; a manifest written before it was recorded implies the papers'
    curvature rule capped at its ``max_dis_between_knots``."""
    if "knot_rule" in manifest:
        try:
            return KnotRule.from_json(manifest["knot_rule"])
        except (TypeError, ValueError) as e:
            raise ExportError(f"corrupt knot_rule in the manifest: {e}") from e
    return KnotRule(max_spacing=float(manifest["max_dis_between_knots"]))


def _finite_or_none(values) -> list:
    return [float(x) if math.isfinite(float(x)) else None for x in np.asarray(values).ravel()]


def observation_layout(n_joints: int, n_path: int, n_next: int,
                       extra: list[tuple[str, int]] = ()) -> list[dict]:
    """Named slices of the observation (docs/method.md §4): ``[{name, start, size}, ...]``; ``extra``:
    the task's sensor blocks ``[(name, size), ...]`` appended at the end."""
    blocks = [("position", n_joints), ("velocity", n_joints), ("acceleration", n_joints),
              ("knots", n_path * (n_next + 1)), ("offset_from_first_knot", 1), ("state_path_length", 1),
              ("knot_distances", n_next), *extra]
    layout, start = [], 0
    for name, size in blocks:
        layout.append({"name": name, "start": start, "size": size})
        start += size
    return layout


def env_observation_layout(env) -> list[dict]:
    """:func:`observation_layout` of a path-tracking environment (its task's blocks included)."""
    return observation_layout(env.limits.n_joints, len(env.path_joints), int(env.config.n_next),
                              env.tracking_extra_blocks() + env.extra_observation_blocks())


def _checked_onnx(policy, exported: jax.export.Exported, obs_size: int) -> tuple[bytes, dict]:
    """``(model bytes, manifest entry)`` of ``policy`` as ONNX, checked against the jax.export
    ``exported`` (:mod:`~mjx_pathtrack.deploy.onnx_policy`); :class:`ExportError` if they differ."""
    from mjx_pathtrack.deploy import onnx_policy as O

    try:
        model = O.policy_to_onnx(policy, obs_size)
    except O.OnnxError as e:
        raise ExportError(str(e)) from e
    diff = O.max_difference(O.OnnxPolicy(model), lambda obs: np.asarray(exported.call(jnp.asarray(obs))))
    if not diff <= O.TOLERANCE:
        raise ExportError(f"the ONNX graph differs from the jax.export policy by {diff:.2e} > {O.TOLERANCE:.0e} "
                          f"on {O.CHECK_OBSERVATIONS} observations")
    return model, {"file": ONNX_FILE, "input": O.INPUT_NAME, "output": O.OUTPUT_NAME,
                   "checked_observations": O.CHECK_OBSERVATIONS, "max_abs_difference": diff}


def _onnx_or_reason(policy, exported: jax.export.Exported, obs_size: int) -> tuple[bytes | None, dict]:
    """:func:`_checked_onnx`, or ``(None, {"file": None, "reason": ...})`` where it fails: the
    jax.export policy stands without an ONNX graph, and the manifest says why."""
    try:
        return _checked_onnx(policy, exported, obs_size)
    except ExportError as e:
        print(f"export: no {ONNX_FILE}: {e}", file=sys.stderr, flush=True)
        return None, {"file": None, "reason": str(e)}


def export_policy(out_dir: str | os.PathLike, make_inference_fn, params, env, robot_name: str,
                  joint_names, run_config: str | None = None, onnx: bool = True) -> Path:
    """Write ``out_dir/{policy.jaxexport, manifest.json}`` for Brax PPO ``params`` on ``env``
    (a :class:`~mjx_pathtrack.envs.tracking.PathTrackingEnv`). ``run_config``: the training run's
    configuration as JSON text (``TrainConfig.to_json()``), recorded as ``run_config`` so that
    ``evaluate.py`` rebuilds the task's environment from an export. ``onnx``: also
    ``policy.onnx``, the same policy as an ONNX graph, written only if jax2onnx converts it and
    it agrees with the jax.export policy within 1e-5 on 10,000 observations; the manifest's
    ``onnx`` entry gives the figure, or why there is no file. Returns ``out_dir``."""
    from mjx_pathtrack import __version__

    out = Path(out_dir)
    inference = make_inference_fn(params, deterministic=True)
    key = jax.random.PRNGKey(0)  # unused by the deterministic policy

    def policy(obs):  # the environment clips actions to [-1, 1]; the export does it itself
        return jnp.clip(inference(obs, key)[0], -1.0, 1.0)

    obs_size, act_size = int(env.observation_size), int(env.action_size)
    batch = jax.export.symbolic_shape("batch")[0]
    exported = jax.export.export(jax.jit(policy))(jax.ShapeDtypeStruct((batch, obs_size), jnp.float32))
    lim = env.limits
    manifest = {
        "format_version": FORMAT_VERSION,
        "package_version": __version__,
        "jax_version": jax.__version__,
        "robot": robot_name,
        "task": env.task_name,
        "joint_names": list(joint_names),
        "path_joints": [int(i) for i in env.path_joints],
        "dt": float(env.config.dt),
        "n_next": int(env.config.n_next),
        **{key: getattr(env.config, key) for key in MANIFEST_ENV_SETTINGS},
        "max_dis_between_knots": float(env.max_dis),
        "knot_rule": env.knot_rule.to_json(),
        "limits": {"pos_min": _finite_or_none(lim.pos_min), "pos_max": _finite_or_none(lim.pos_max),
                   "vel": _finite_or_none(lim.vel), "acc": _finite_or_none(lim.acc),
                   "jerk": _finite_or_none(lim.jerk)},
        "observation_size": obs_size,
        "action_size": act_size,
        "observation_layout": env_observation_layout(env),
        "input": {"shape": ["batch", obs_size], "dtype": "float32", "range": [-1.0, 1.0]},
        "output": {"shape": ["batch", act_size], "dtype": "float32", "range": [-1.0, 1.0],
                   "meaning": "action per joint, mapped into the safe acceleration range"},
    }
    if run_config is not None:
        manifest["run_config"] = json.loads(run_config)
    onnx_model = None
    if onnx:
        onnx_model, manifest["onnx"] = _onnx_or_reason(policy, exported, obs_size)
    atomic_write_bytes(out / POLICY_FILE, bytes(exported.serialize()))
    if onnx_model is not None:
        atomic_write_bytes(out / ONNX_FILE, onnx_model)
    atomic_write_bytes(out / MANIFEST_FILE, (json.dumps(manifest, indent=2) + "\n").encode())
    return out


@dataclass(frozen=True)
class ExportedPolicy:
    """A loaded export: call it with observations ``[B, obs_size]`` (or ``[obs_size]``) to get
    actions ``[B, n]`` (or ``[n]``) in [-1, 1]."""

    manifest: dict
    _exported: jax.export.Exported

    @property
    def observation_size(self) -> int:
        return int(self.manifest["observation_size"])

    @cached_property
    def _jitted(self):
        """The export's call, compiled once per batch size (the host side of :meth:`traced_call`)."""
        return jax.jit(self._exported.call)

    def traced_call(self, obs: jax.Array) -> jax.Array:
        """The policy inside a larger jitted program (an evaluation rollout): ``obs [B,
        obs_size]`` float32 -> actions ``[B, n]`` in [-1, 1], computed by the export in a program
        of its own (a host callback), exactly as :meth:`__call__` computes them.

        Why not the export's own ``call`` inline: the stored export accepts any batch size (a
        symbolic dimension), and a program that calls it gets the shapes of the *whole* program
        refined by JAX. With jax 0.9.2 that refinement changed the MJX physics compiled beside
        the policy (the full-arm ball scene's arm lagged its setpoints by 0.02 rad instead of
        2e-4 rad and the ball fell in every episode); re-exporting at a concrete batch size still
        carries the refinement along. Kept apart, the two programs compute what they compute
        alone."""
        shape = tuple(obs.shape)
        if len(shape) != 2 or shape[1] != self.observation_size:
            raise ExportError(f"observation must have shape [B, {self.observation_size}] for robot "
                              f"{self.manifest['robot']}, got {shape}")
        run = self._jitted
        out = jax.ShapeDtypeStruct((shape[0], int(self.manifest["action_size"])), jnp.float32)
        return jax.pure_callback(lambda o: np.asarray(run(o), np.float32), out, jnp.asarray(obs, jnp.float32))

    def __call__(self, obs) -> np.ndarray:
        batch, single = observation_batch(obs, self.observation_size, ExportError, f"for robot {self.manifest['robot']}")
        if not np.all(np.isfinite(batch)):
            raise ExportError("observation contains NaN or inf")
        action = np.asarray(self._exported.call(jnp.asarray(batch)))
        return action[0] if single else action


def attach_onnx(path: str | os.PathLike, policy) -> dict:
    """Add ``policy.onnx`` to the export directory ``path`` written before exports held one:
    ``policy`` (jittable ``obs [B, obs_size] -> actions [B, n]`` in [-1, 1], rebuilt from the
    run's parameters) converted and checked against the directory's own ``policy.jaxexport``,
    the file written if it agrees within 1e-5, and the manifest's ``onnx`` entry (the figure, or
    why there is no file) in any case. Returns that entry."""
    root = Path(path)
    loaded = load_policy(root)
    model, entry = _onnx_or_reason(policy, loaded._exported, loaded.observation_size)
    if model is not None:
        atomic_write_bytes(root / ONNX_FILE, model)
    manifest = {**loaded.manifest, "onnx": entry}
    atomic_write_bytes(root / MANIFEST_FILE, (json.dumps(manifest, indent=2) + "\n").encode())
    return entry


def load_policy(path: str | os.PathLike) -> ExportedPolicy:
    """Load an export directory written by :func:`export_policy` (needs only jax and numpy)."""
    root = Path(path)
    manifest_file, policy_file = root / MANIFEST_FILE, root / POLICY_FILE
    if not root.is_dir():
        raise ExportError(f"no exported policy at {root} (directory missing)")
    for f in (manifest_file, policy_file):
        if not f.is_file():
            raise ExportError(f"incomplete export at {root}: {f.name} missing")
    try:
        manifest = json.loads(manifest_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ExportError(f"corrupt manifest {manifest_file}: {e}") from e
    if not isinstance(manifest, dict):
        raise ExportError(f"{manifest_file}: not a manifest (a JSON object), got {type(manifest).__name__}")
    version = manifest.get("format_version")
    if version != FORMAT_VERSION:
        raise ExportError(f"{manifest_file}: export format version {version}, this package reads {FORMAT_VERSION}")
    for key, (kind, what) in REQUIRED_KEYS.items():
        value = manifest.get(key)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise ExportError(f"{manifest_file}: key {key!r} is {'missing' if value is None else repr(value)}, "
                              f"must be {what}")
    try:
        exported = jax.export.deserialize(bytearray(policy_file.read_bytes()))
    except Exception as e:  # flatbuffer / version errors of jax.export
        raise ExportError(f"corrupt or incompatible policy file {policy_file} (exported with jax "
                          f"{manifest.get('jax_version')}, running {jax.__version__}): {e}") from e
    shape = exported.in_avals[0].shape
    if len(shape) != 2 or int(shape[1]) != manifest["observation_size"]:
        raise ExportError(f"{policy_file}: input shape {shape} does not match the manifest's "
                          f"observation size {manifest['observation_size']}")
    return ExportedPolicy(manifest, exported)
