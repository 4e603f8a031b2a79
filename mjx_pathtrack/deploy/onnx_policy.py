"""The deterministic policy as an ONNX graph, for controllers without JAX (C++, ros2_control).

:func:`policy_to_onnx` converts the same function that ``policy.jaxexport`` holds (observation
normalisation, network, tanh mean, clip to [-1, 1]) with ``jax2onnx`` -- traced, not written by
hand -- into a graph with one input ``observation [batch, obs_size]`` float32 and one output
``action [batch, n]`` float32. :func:`max_difference` measures it against a reference policy on
random observations; :func:`~mjx_pathtrack.deploy.export.export_policy` writes ``policy.onnx``
only when that difference is at most :data:`TOLERANCE` on :data:`CHECK_OBSERVATIONS`
observations and records both in the manifest. :class:`OnnxPolicy` runs the file with numpy and
``onnxruntime`` alone (README "Deploy without JAX")::

    import numpy as np, onnxruntime as ort
    session = ort.InferenceSession("export/policy.onnx")
    action = session.run(["action"], {"observation": obs.astype(np.float32)})[0]   # obs [B, obs_size]
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

ONNX_FILE = "policy.onnx"
INPUT_NAME = "observation"
OUTPUT_NAME = "action"
#: observations on which an ONNX graph is checked against the jax.export policy
CHECK_OBSERVATIONS = 10_000
#: largest accepted absolute action difference between the ONNX graph and the jax.export policy
TOLERANCE = 1e-5


class OnnxError(ValueError):
    """An ONNX policy that cannot be made, loaded or trusted (the message says which)."""


def policy_to_onnx(policy: Callable, obs_size: int, name: str = "mjx_pathtrack_policy") -> bytes:
    """The serialized ONNX model of ``policy`` (a jittable ``obs [B, obs_size] float32 -> actions
    [B, n]``), with a symbolic batch dimension and the inputs and outputs named
    :data:`INPUT_NAME` and :data:`OUTPUT_NAME`; :class:`OnnxError` if jax2onnx cannot convert it.

    Known limit (jax2onnx 0.17.1): a policy with an action prior that computes the safe
    acceleration range (ARMAR-4's ``--leg-prior hold``) is refused. The range's stopping search
    (``core.stopping``, ``core.compaction``) takes shapes with ``jnp.shape``, which jax2onnx
    traces as values (the first error), compacts lanes with ``custom_vmap`` and a
    data-dependent loop, and runs ``lax.fori_loop`` bodies that close over traced arrays, which
    jax2onnx's loop lowering needs concrete (``plugins/jax/lax/fori_loop.py`` calls
    ``np.asarray`` on them; measured with the first two worked around). It would take static
    shapes, an uncompacted path and loops that carry those arrays in their state."""
    from jax2onnx import to_onnx

    try:
        model = to_onnx(policy, [("batch", int(obs_size))], model_name=name)
    except Exception as e:  # jax2onnx raises many types for constructs it cannot lower
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise OnnxError(f"jax2onnx cannot convert this policy: {type(e).__name__}: {first[:300]}") from e
    graph = model.graph
    if len(graph.input) != 1 or len(graph.output) != 1:
        raise OnnxError(f"expected one input and one output, jax2onnx made {len(graph.input)} and {len(graph.output)}")
    rename = {graph.input[0].name: INPUT_NAME, graph.output[0].name: OUTPUT_NAME}
    for node in graph.node:
        for names in (node.input, node.output):
            for i, value in enumerate(names):
                if value in rename:
                    names[i] = rename[value]
    graph.input[0].name, graph.output[0].name = INPUT_NAME, OUTPUT_NAME
    return model.SerializeToString()


class OnnxPolicy:
    """An ONNX policy file (or its bytes) run by ``onnxruntime`` on the CPU: call it with
    observations ``[B, obs_size]`` (or ``[obs_size]``) float32 in [-1, 1] to get actions ``[B, n]``
    (or ``[n]``) in [-1, 1]."""

    def __init__(self, model: str | os.PathLike | bytes):
        import onnxruntime as ort

        source = model if isinstance(model, bytes) else str(Path(model))
        if not isinstance(model, bytes) and not Path(model).is_file():
            raise OnnxError(f"no ONNX policy at {model}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1   # one decision at a time on a robot's computer
        try:
            self.session = ort.InferenceSession(source, options, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types for corrupt files
            raise OnnxError(f"corrupt ONNX policy {model if not isinstance(model, bytes) else '(bytes)'}: {e}") from e
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        if [i.name for i in inputs] != [INPUT_NAME] or [o.name for o in outputs] != [OUTPUT_NAME]:
            raise OnnxError(f"not a policy graph: inputs {[i.name for i in inputs]}, outputs {[o.name for o in outputs]} "
                            f"(expected [{INPUT_NAME!r}] and [{OUTPUT_NAME!r}])")
        self.observation_size = int(inputs[0].shape[1])

    def __call__(self, obs) -> np.ndarray:
        batch, single = observation_batch(obs, self.observation_size, OnnxError)
        action = self.session.run([OUTPUT_NAME], {INPUT_NAME: batch})[0]
        return action[0] if single else action


def observation_batch(obs, size: int, error: type[Exception], owner: str = "") -> tuple[np.ndarray, bool]:
    """``(batch [B, size] float32, single)`` of observations given as ``[size]`` (``single``) or
    ``[B, size]``; ``error`` (naming ``owner``, e.g. "for robot iiwa") for any other shape."""
    obs = np.asarray(obs, np.float32)
    single = obs.ndim == 1
    batch = obs[None] if single else obs
    if batch.ndim != 2 or batch.shape[1] != size:
        raise error(f"observation must have shape [{size}] or [B, {size}]{' ' + owner if owner else ''}, got {obs.shape}")
    return batch, single


def check_observations(obs_size: int, count: int = CHECK_OBSERVATIONS, seed: int = 0) -> np.ndarray:
    """``[count, obs_size]`` float32 observations for an agreement check: uniform in [-1, 1] (the
    clipped observation range), with the first rows at the corners ±1 and 0."""
    rng = np.random.default_rng(seed)
    obs = rng.uniform(-1.0, 1.0, (count, obs_size)).astype(np.float32)
    corners = np.stack([np.ones(obs_size), -np.ones(obs_size), np.zeros(obs_size),
                        np.where(np.arange(obs_size) % 2 == 0, 1.0, -1.0)]).astype(np.float32)
    obs[:min(count, len(corners))] = corners[:count]
    return obs


def max_difference(onnx_policy: OnnxPolicy, reference: Callable[[np.ndarray], np.ndarray],
                   count: int = CHECK_OBSERVATIONS, seed: int = 0, chunk: int = 2048) -> float:
    """Largest absolute action difference between ``onnx_policy`` and ``reference`` (observations
    ``[B, obs_size]`` float32 -> actions ``[B, n]``) over :func:`check_observations`."""
    obs = check_observations(onnx_policy.observation_size, count, seed)
    worst = 0.0
    for i in range(0, count, chunk):
        part = obs[i:i + chunk]
        a, b = onnx_policy(part), np.asarray(reference(part), np.float32)
        if a.shape != b.shape:
            raise OnnxError(f"ONNX actions {a.shape} against reference {b.shape}")
        if not np.all(np.isfinite(a)):
            raise OnnxError("the ONNX policy returned NaN or inf")
        worst = max(worst, float(np.max(np.abs(a - b))))
    return worst
