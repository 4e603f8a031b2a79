import atexit
import os
import shutil
import tempfile

import mjx_pathtrack

# Batched MJX on CPU needs the XLA flag before JAX starts (mjx_pathtrack/_xla.py); every test
# process (and the subprocesses tests start, which inherit it) runs with it, as the entry points do.
mjx_pathtrack.prepare_xla()

os.environ.setdefault("MPLBACKEND", "Agg")
# Offscreen OpenGL for the rendering tests (tests/evaluation/test_video.py): read when mujoco is imported.
os.environ.setdefault("MUJOCO_GL", "egl")

# One persistent XLA compilation cache per test process (also inherited by the subprocesses a
# test starts): the training tests compile the same PPO program several times. Set before JAX is
# imported. Under pytest-xdist every worker gets its own directory (the workers inherit the
# controller's environment): JAX writes cache entries without a lock, so two processes must not
# share one. A cache directory the user set is left alone.
_OWNER = "MJX_PATHTRACK_TEST_CACHE_OWNER"
if "JAX_COMPILATION_CACHE_DIR" not in os.environ or os.environ.get(_OWNER, str(os.getpid())) != str(os.getpid()):
    _cache = tempfile.mkdtemp(prefix="mjx_pathtrack_xla_cache_")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    os.environ[_OWNER] = str(os.getpid())
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
