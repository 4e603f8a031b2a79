"""Deployment: the exported jitted policy and the online controller that runs it.

- :mod:`~mjx_pathtrack.deploy.export`: ``export_policy`` / ``load_policy`` (a directory with a manifest);
- :mod:`~mjx_pathtrack.deploy.onnx_policy`: the same policy as an ONNX graph, run with onnxruntime alone;
- :mod:`~mjx_pathtrack.deploy.controller`: ``OnlineTracker``, the policy in a real-time loop.
"""
