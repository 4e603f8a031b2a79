"""configure_xla_flags: appends the CPU fusion-emitter flag without clobbering the user's XLA_FLAGS."""

import os
import subprocess
import sys

import pytest

from mjx_pathtrack._xla import (
    ADDED_VAR,
    FUSION_FLAG,
    OPT_OUT_VAR,
    configure_xla_flags,
    drop_cpu_fix,
    jaxlib_knows_flag,
    prepare,
    xla_flags_with_cpu_fix,
)

USER_FLAG = "--xla_force_host_platform_device_count=2"


def test_sets_flag_when_unset():
    env = {}
    assert configure_xla_flags(env)
    assert env["XLA_FLAGS"] == FUSION_FLAG


def test_appends_to_existing_flags():
    env = {"XLA_FLAGS": f"{USER_FLAG} --xla_dump_to=/tmp/x"}
    configure_xla_flags(env)
    assert env["XLA_FLAGS"] == f"{USER_FLAG} --xla_dump_to=/tmp/x {FUSION_FLAG}"


def test_idempotent():
    env = {"XLA_FLAGS": USER_FLAG}
    assert configure_xla_flags(env)
    once = env["XLA_FLAGS"]
    assert not configure_xla_flags(env)
    assert env["XLA_FLAGS"] == once
    assert once.split().count(FUSION_FLAG) == 1


@pytest.mark.parametrize(
    "flags",
    [
        "--xla_cpu_use_fusion_emitters=true",
        f"{USER_FLAG} --xla_cpu_use_fusion_emitters=1",
        "--xla_cpu_use_fusion_emitters",
    ],
)
def test_respects_explicit_user_value(flags):
    env = {"XLA_FLAGS": flags}
    assert not configure_xla_flags(env)
    assert env["XLA_FLAGS"] == flags


@pytest.mark.parametrize("value", ["1", "true", "yes"])
def test_opt_out(value):
    env = {"XLA_FLAGS": USER_FLAG, OPT_OUT_VAR: value}
    assert not configure_xla_flags(env)
    assert env["XLA_FLAGS"] == USER_FLAG


@pytest.mark.parametrize(
    "version, knows",
    [("0.9.2", True), ("0.10.2", True), ("0.11.2", False), ("0.12.0.1", False), ("1.0.0", False),
     (None, True), ("dev", True)],
)
def test_flag_only_for_jaxlib_that_knows_it(version, knows):
    # jaxlib 0.11.2's XLA aborts the process on the unknown flag (measured), so never add it there.
    assert jaxlib_knows_flag(version) is knows
    expected = FUSION_FLAG if knows else None
    assert xla_flags_with_cpu_fix({}, version) == expected


def test_opt_out_zero_does_not_opt_out():
    env = {OPT_OUT_VAR: "0"}
    assert configure_xla_flags(env)


@pytest.mark.parametrize(
    "platform_env",
    [
        {"JAX_PLATFORMS": "cuda"},
        {"JAX_PLATFORMS": "gpu"},
        {"JAX_PLATFORMS": "tpu"},
        {"JAX_PLATFORMS": "cuda,rocm"},
        {"JAX_PLATFORM_NAME": "gpu"},
    ],
)
def test_non_cpu_platform_left_alone(platform_env):
    env = {"XLA_FLAGS": USER_FLAG, **platform_env}
    assert not configure_xla_flags(env)
    assert env["XLA_FLAGS"] == USER_FLAG


@pytest.mark.parametrize(
    "platform_env",
    [{"JAX_PLATFORMS": "cpu"}, {"JAX_PLATFORMS": "cuda,cpu"}, {"JAX_PLATFORMS": ""}, {"JAX_PLATFORM_NAME": "cpu"}],
)
def test_cpu_platform_gets_flag(platform_env):
    env = dict(platform_env)
    assert configure_xla_flags(env)
    assert env["XLA_FLAGS"] == FUSION_FLAG


@pytest.mark.parametrize("user_flags", ["", USER_FLAG, f"{USER_FLAG} --xla_dump_to=/tmp/x"])
def test_drop_takes_out_exactly_the_flag_this_package_added(user_flags):
    env = {"XLA_FLAGS": user_flags} if user_flags else {}
    assert configure_xla_flags(env)
    assert env[ADDED_VAR] == FUSION_FLAG
    assert drop_cpu_fix(env)
    assert env == ({"XLA_FLAGS": user_flags} if user_flags else {})
    assert not drop_cpu_fix(env)  # nothing left to take out


@pytest.mark.parametrize("flags", [FUSION_FLAG, f"{USER_FLAG} {FUSION_FLAG}"])
def test_drop_keeps_a_users_own_flag(flags):
    env = {"XLA_FLAGS": flags}
    assert not configure_xla_flags(env)  # the user chose a value: not ours
    assert not drop_cpu_fix(env)
    assert env == {"XLA_FLAGS": flags}


def _run(code):
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_PLATFORMS", "JAX_PLATFORM_NAME", OPT_OUT_VAR, ADDED_VAR)}
    env["XLA_FLAGS"] = USER_FLAG
    env["JAX_PLATFORMS"] = "cpu"
    result = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


def test_import_changes_nothing_and_prints_nothing():
    out = _run("import os, sys, io, contextlib\n"
               "before = dict(os.environ)\n"
               "buf = io.StringIO()\n"
               "with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):\n"
               "    import mjx_pathtrack\n"
               "print(dict(os.environ) == before, repr(buf.getvalue()))")
    assert out == "True ''"
    result = subprocess.run([sys.executable, "-c", "import mjx_pathtrack"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0 and result.stdout == "" and result.stderr == ""


def test_prepare_appends_flag_in_subprocess():
    flags = _run("import mjx_pathtrack, os; mjx_pathtrack.prepare_xla(); print(os.environ['XLA_FLAGS'])").split()
    assert USER_FLAG in flags
    assert FUSION_FLAG in flags


def test_user_flag_takes_effect_after_prepare():
    out = _run(
        "import warnings; warnings.simplefilter('error')\n"
        "import mjx_pathtrack; mjx_pathtrack.prepare_xla(); import jax\n"
        "print(len(jax.devices()))"
    )
    assert out == "2"


def test_warns_when_backend_already_initialized():
    out = _run(
        "import warnings, jax; jax.devices()\n"
        "import mjx_pathtrack\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    mjx_pathtrack.prepare_xla()\n"
        "print(sum('could not take effect' in str(x.message) for x in w))"
    )
    assert out == "1"


def test_no_warning_when_jax_imported_but_unused():
    out = _run(
        "import warnings, jax\n"
        "import mjx_pathtrack\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    mjx_pathtrack.prepare_xla()\n"
        "print(len(w), len(jax.devices()))"
    )
    assert out == "0 2"


def test_prepare_without_mjx_drops_only_the_flag_a_parent_added():
    env = {"XLA_FLAGS": USER_FLAG}
    assert configure_xla_flags(env)  # what a parent process did
    assert prepare(mjx_physics=False, environ=env)
    assert env == {"XLA_FLAGS": USER_FLAG}
    own = {"XLA_FLAGS": FUSION_FLAG}
    assert not prepare(mjx_physics=False, environ=own) and own == {"XLA_FLAGS": FUSION_FLAG}


def test_mjx_executor_warns_without_the_flag_and_names_the_fix():
    code = ("import warnings\n"
            "from mjx_pathtrack.envs.executors import MjxExecutor\n"
            "from mjx_pathtrack.robots.registry import load_robot\n"
            "robot = load_robot('iiwa')\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    MjxExecutor(robot)\n"
            "print(sum('prepare_xla()' in str(x.message) for x in w))")
    assert _run(code) == "1"  # _run's environment has the user's flag only
    assert _run("import mjx_pathtrack; mjx_pathtrack.prepare_xla()\n" + code) == "0"


def test_drop_in_a_fresh_process_only_before_the_backend_starts():
    out = _run("import mjx_pathtrack, os; from mjx_pathtrack import _xla; mjx_pathtrack.prepare_xla()\n"
               "print(_xla.drop_cpu_fix(), os.environ['XLA_FLAGS'])")
    assert out == f"True {USER_FLAG}"
    out = _run("import mjx_pathtrack, os, jax; from mjx_pathtrack import _xla; mjx_pathtrack.prepare_xla(); jax.devices()\n"
               "print(_xla.drop_cpu_fix(), _xla.FUSION_FLAG in os.environ['XLA_FLAGS'].split())")
    assert out == "False True"  # too late: XLA has read its flags


def test_paths_command_line_sets_the_flag_before_jax_starts():
    """``python -m mjx_pathtrack.paths`` runs MJX kinematics (IK, collision) when it generates or
    imports paths: it must set the flag like the other entry points (without it a target-point
    split ran 45 min unfinished, against 6.5 min with it)."""
    out = _run("import os, runpy, sys\n"
               "sys.argv = ['mjx_pathtrack.paths', '--help']\n"
               "try:\n"
               "    runpy.run_module('mjx_pathtrack.paths', run_name='__main__')\n"
               "except SystemExit:\n"
               "    pass\n"
               "print('FLAGS', os.environ.get('XLA_FLAGS', ''))")
    flags = out.split("FLAGS", 1)[1].split()
    assert FUSION_FLAG in flags and USER_FLAG in flags
