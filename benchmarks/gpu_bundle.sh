#!/usr/bin/env bash
# Builds .whl/, what benchmarks/gpu_session.sh carries to the lent GPU machine (which has Python 3.12,
# JAX with CUDA and NumPy/SciPy preinstalled, and no internet): cp312 wheels of the pinned physics and
# RL packages and their pure-Python dependencies the machine lacks (no dependency resolution there:
# --no-deps), and .whl/armar4_slim.tgz, the armar package with only the files the ARMAR-4 URDFs name
# (the whole package is 150 MB; the carry limit is 64 MB). Run it once in a checkout whose venv has
# the test extras (armar installed); pass it to the device tool as carry: [".whl"].
set -euo pipefail
cd "$(dirname "$(readlink -f "${BASH_SOURCE[0]}")")/.."
mkdir -p .whl
# the versions this venv has (pyproject's pins and what they resolved to)
mapfile -t PKGS < <(python - <<'PY'
from importlib.metadata import version
for name in ("mujoco", "mujoco-core", "mujoco-studio", "mujoco-mjx", "brax", "klimits", "toppra", "jaxopt",
             "ml_collections", "tensorboardX", "trimesh", "yourdfpy", "glfw", "PyOpenGL", "flask", "flask-cors",
             "blinker", "itsdangerous"):
    print(f"{name}=={version(name)}")
PY
)
rm -f .whl/*.whl
python -m pip download -q --no-deps --only-binary=:all: --implementation cp --python-version 3.12 \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .whl "${PKGS[@]}"
python - <<'EOF'
"""armar4_slim.tgz: the armar package's Python files and the ARMAR-4 URDFs with the meshes they name."""
import os
import re
import tarfile

import armar

root = os.path.dirname(armar.__file__)
urdf_dir = os.path.join(root, "description", "urdf")
keep = set()
for name in os.listdir(urdf_dir):
    if name.startswith("armar4") and name.endswith(".urdf"):
        path = os.path.join(urdf_dir, name)
        keep.add(path)
        for ref in re.findall(r'filename="([^"]+)"', open(path).read()):
            ref = re.sub(r"^package://[^/]+/", "", ref)
            for candidate in (os.path.normpath(os.path.join(urdf_dir, ref)), os.path.normpath(os.path.join(root, ref))):
                if os.path.exists(candidate):
                    keep.add(candidate)
                    break
            else:
                raise SystemExit(f"{name}: mesh {ref!r} not found under {root}")
for folder, _, files in os.walk(root):
    keep.update(os.path.join(folder, f) for f in files if f.endswith(".py"))
with tarfile.open(".whl/armar4_slim.tgz", "w:gz") as tar:
    for path in sorted(keep):
        tar.add(path, arcname=os.path.join("armar", os.path.relpath(path, root)))
print(f"armar4_slim.tgz: {len(keep)} files")
EOF
du -sh .whl
