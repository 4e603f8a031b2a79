"""Rendered rollouts (mjx_pathtrack.evaluation.video): what the frames show is where the robot,
its path and the ball are, the frames are not blank, the drawn path is visible, and the files
written are complete videos. Offscreen OpenGL: MUJOCO_GL=egl (tests/conftest.py)."""

import dataclasses
import io
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from PIL import Image

from mjx_pathtrack.core import spline as S
from mjx_pathtrack.envs.tracking import EnvConfig, PathTrackingEnv
from mjx_pathtrack.evaluation import rollout as E
from mjx_pathtrack.evaluation import video as V
from mjx_pathtrack.robots import registry as robots

DT = 0.1
SMALL = V.VideoSettings(width=160, height=128, fps=10)


def _policy(obs, key):
    """Joint 1 as fast as allowed, joint 2 slowly, the others held."""
    return jnp.zeros((obs.shape[0], 7)).at[:, 0].set(1.0).at[:, 1].set(0.3)


@pytest.fixture(scope="module")
def iiwa():
    return robots.load_robot("iiwa", dt=DT)


@pytest.fixture(scope="module")
def episode(iiwa):
    """Two whole-path episodes on a bent path of joints 1 and 2 (kinematic executor)."""
    knots = np.zeros((6, 7))
    knots[:, 0] = np.linspace(0.0, 1.2, 6)
    knots[:, 1] = 0.5 + 0.2 * np.sin(np.linspace(0.0, 2.0, 6))
    cfg = EnvConfig(start_range=(0.0, 0.0), min_fraction=1.0, max_fraction=1.0, terminate_deviation=None,
                    duration=2.0)
    env = PathTrackingEnv(iiwa.limits, S.stack_paths([S.make_path(knots)] * 2), 0.9, cfg, home=iiwa.q0)
    return env, E.rollout(env, _policy, jax.random.PRNGKey(0), [0, 1])


def _tool(model, qpos, site):
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    return data.site_xpos[site].copy()


def _blue(frame):
    """Pixels of the reference path's blue (shaded and anti-aliased: by hue, not by exact colour)."""
    r, g, b = np.moveaxis(frame.astype(int), -1, 0)
    return int(np.sum((b - r > 60) & (b - g > 40)))


def _orange(frame):
    """Pixels of the executed trace's orange."""
    r, g, b = np.moveaxis(frame.astype(int), -1, 0)
    return int(np.sum((r - b > 80) & (r - g > 60) & (g - b > 40)))


def test_scene_follows_the_recorded_motion(episode, iiwa):
    env, ro = episode
    scene = V.episode_scene(env, ro, iiwa, 0, SMALL)
    steps = int(ro.live[:, 0].sum())
    poly = E.executed_polyline(ro, 0)
    assert len(scene.time) == int(steps * DT * SMALL.fps) + 1 and scene.time[1] == pytest.approx(0.1)
    # each frame shows the executed pose of its instant, and the last frame the episode's end
    np.testing.assert_allclose(scene.qpos[:, iiwa.qpos_adr], poly[scene.sub], atol=1e-6)
    np.testing.assert_allclose(scene.qpos[-1, iiwa.qpos_adr], poly[-1], atol=1e-6)
    site = scene.sites[0]
    np.testing.assert_allclose(scene.trace[-1, 0], _tool(scene.model, scene.qpos[-1], site), atol=1e-9)
    # the reference tool curve starts where the robot starts and ends at the path's end knot
    end = np.asarray(iiwa.q0, np.float64).copy()
    end[:2] = [1.2, 0.5 + 0.2 * np.sin(2.0)]
    np.testing.assert_allclose(scene.reference[0, 0], scene.trace[0, 0], atol=1e-6)
    np.testing.assert_allclose(scene.reference[0, -1], _tool(scene.model, end, site), atol=1e-5)
    # the caption's numbers are the recorded ones
    assert scene.progress[0] == 0 and scene.progress[-1] == pytest.approx(float(ro.progress[steps - 1, 0]))
    assert np.all(np.isnan(scene.ball)) and scene.ball_world is None


def test_frames_show_the_robot_the_path_and_the_growing_trace(episode, iiwa):
    env, ro = episode
    scene = V.episode_scene(env, ro, iiwa, 1, SMALL, title="test")
    frames = V.render_frames(scene, SMALL)
    assert frames.shape == (len(scene.time), 128, 160, 3) and frames.dtype == np.uint8
    below = frames[:, :-40]   # above the caption band
    assert below.std() > 20, "blank frames"
    assert np.abs(frames[0, :-40].astype(int) - frames[-1, :-40].astype(int)).sum() > 0, "the robot did not move"
    blue = [_blue(f) for f in below]
    orange = [_orange(f) for f in below]
    assert min(blue) > 20, "the reference path is not visible"
    assert orange[-1] > 20 and orange[-1] > orange[1], "the executed trace does not grow"


def test_ball_is_placed_on_the_plate_from_its_plate_frame_record(episode, iiwa):
    """A ball record (what every ball executor keeps: the centre in the plate frame) is drawn in the
    iiwa_ball scene at plate position + plate rotation @ record, interpolated between decisions."""
    env, ro = episode
    steps = ro.live.shape[0]
    local = np.zeros((steps, 2, 3))
    local[:, :, 0] = np.linspace(0.0, 0.1, steps)[:, None]   # rolls 10 cm along the plate's x axis
    local[:, :, 2] = 0.02
    scene = V.episode_scene(env, ro._replace(scene={"ball": local}), iiwa, 0, SMALL)
    model = scene.model
    plate = model.site("plate").id
    adr = int(model.jnt_qposadr[model.joint("ball").id])
    for f in (0, len(scene.time) // 2, len(scene.time) - 1):
        data = mujoco.MjData(model)
        data.qpos[:] = scene.qpos[f]
        mujoco.mj_kinematics(model, data)
        k = min(int(scene.time[f] / DT + 1e-9), int(ro.live[:, 0].sum()) - 1)
        frac = scene.time[f] / DT - k
        expected_local = (1 - frac) * local[max(k - 1, 0), 0] + frac * local[k, 0]
        expected = data.site_xpos[plate] + data.site_xmat[plate].reshape(3, 3) @ expected_local
        np.testing.assert_allclose(scene.qpos[f, adr:adr + 3], expected, atol=1e-6)
        assert scene.ball[f] == pytest.approx(abs(expected_local[0]), abs=1e-9)
    # the ball is drawn: moving it out of view changes the picture (first frame: the plate still
    # faces the camera; this test path tilts it later)
    first = dataclasses.replace(scene, qpos=scene.qpos[:1])
    hidden = first.qpos.copy()
    hidden[:, adr + 2] = -5.0
    shown = V.render_frames(first, SMALL)[0]
    gone = V.render_frames(dataclasses.replace(first, qpos=hidden), SMALL)[0]
    assert np.sum(np.any(shown != gone, axis=-1)) > 10, "the ball is not visible"


@pytest.mark.parametrize("suffix", [".mp4", ".gif", ".png"])
def test_written_files_are_complete(tmp_path, suffix):
    frames = np.zeros((7, 32, 48, 3), np.uint8)
    frames[:, :, :, 0] = np.arange(7)[:, None, None] * 30   # a different red per frame
    path = V.write_video(tmp_path / f"clip{suffix}", frames, fps=10)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]   # no temporary file left behind
    if suffix == ".mp4":
        import imageio_ffmpeg

        reader = imageio_ffmpeg.read_frames(str(path))
        with warnings.catch_warnings():   # ffmpeg is started with fork + exec
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
            meta = next(reader)
        got = [np.frombuffer(f, np.uint8).reshape(32, 48, 3) for f in reader]
        assert meta["size"] == (48, 32) and meta["fps"] == 10 and len(got) == 7
        assert abs(int(got[-1][..., 0].mean()) - 180) < 12   # lossy, but the last frame's red
    else:
        image = Image.open(io.BytesIO(path.read_bytes()))
        assert image.size == (48, 32)
        assert getattr(image, "n_frames", 1) == (7 if suffix == ".gif" else 1)
        if suffix == ".png":
            assert np.asarray(image.convert("RGB"))[0, 0, 0] == 180   # the last frame


def test_bad_requests_name_the_problem(tmp_path, episode, iiwa):
    env, ro = episode
    with pytest.raises(V.RenderError, match=r"must end in \.mp4 / \.gif / \.png"):
        V.write_video(tmp_path / "clip.avi", np.zeros((1, 16, 16, 3), np.uint8), 10)
    with pytest.raises(V.RenderError, match=r"frames must have shape"):
        V.write_video(tmp_path / "clip.gif", np.zeros((0, 16, 16, 3), np.uint8), 10)
    with pytest.raises(V.RenderError, match="episode 5 is not in the rendered batch of 2"):
        V.episode_scene(env, ro, iiwa, 5)
    with pytest.raises(V.RenderError, match="video size"):
        V.VideoSettings(width=8)
    assert not list(tmp_path.iterdir())
