"""Rendered rollouts: one evaluated episode as a video, offscreen with MuJoCo's renderer.

``evaluate.py RUN --video [FILE]`` calls :func:`write_episode_video` on episodes of the batch it
evaluated (nothing is rendered without the flag). A frame shows

* the robot in its executed pose (the sub-step positions the evaluation recorded; with an MJX
  executor the whole scene's pose after each decision step, so a floating base and joints the
  policy does not drive move as simulated, interpolated between decision steps);
* the ball on the plate (ball tasks: its recorded position in the plate frame, interpolated
  between decision steps and placed on the plate of the rendered pose);
* the reference path of every target point (tool) as a blue line, from the episode's start to its
  end (with user paths: the user's curve), and the executed trace so far in orange;
* a caption: time [s], path progress, the last step's largest weighted deviation [rad] (and the
  ball's distance from the plate centre).

Frames come at ``fps`` from the recorded motion (no re-simulation). Files: ``.mp4`` (H.264 via
the ``ffmpeg`` that ``imageio-ffmpeg`` ships), ``.gif`` (Pillow) or ``.png`` (the last frame:
the whole executed trace), written atomically.

Offscreen rendering needs an OpenGL back end without a display: ``MUJOCO_GL=egl`` (or
``osmesa``) in the environment *before* ``mujoco`` is imported (``evaluate.py --video`` sets
``egl`` unless ``MUJOCO_GL`` is set).
"""

from __future__ import annotations

import dataclasses
import io
import os
import warnings
from pathlib import Path as FsPath

import numpy as np

from mjx_pathtrack.evaluation import rollout as E
from mjx_pathtrack.fileio import atomic_write, atomic_write_bytes

#: file types :func:`write_video` writes
VIDEO_SUFFIXES = (".mp4", ".gif", ".png")
#: colours (RGBA) of the reference path and of the executed trace
REFERENCE_RGBA = (0.15, 0.45, 0.95, 0.9)
TRACE_RGBA = (1.0, 0.45, 0.05, 1.0)
#: at most this many drawn segments per curve (longer curves are thinned evenly)
MAX_SEGMENTS = 400


class RenderError(RuntimeError):
    """Rendering is not possible here or the request is invalid (one line, names the cause)."""


@dataclasses.dataclass(frozen=True)
class VideoSettings:
    """Frame size [px] (multiples of 16 keep H.264 exact), frame rate [1/s], camera angles [deg]
    (``distance`` [m]: None fits the robot and its path), width [px] of the drawn reference path
    (the executed trace 1 px wider)."""

    width: int = 640
    height: int = 480
    fps: int = 30
    azimuth: float = 135.0
    elevation: float = -20.0
    distance: float | None = None
    line_width: float = 3.0

    def __post_init__(self):
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise RenderError(f"video size must be 16..4096 px per side, got {self.width}x{self.height}")
        if not 1 <= self.fps <= 240:
            raise RenderError(f"video frame rate must be 1..240, got {self.fps}")


@dataclasses.dataclass(frozen=True)
class EpisodeScene:
    """What the frames of one episode show. ``model``: the rendered ``mujoco.MjModel``;
    ``qpos [F, nq]`` per frame; ``time [F]`` [s]; ``sub [F]``: the recorded sub-step each frame
    shows; ``progress``, ``deviation [F]``; ``ball [F]`` distance of the ball from the plate centre
    [m] (NaN without a ball); ``ball_world [F, 3]`` or None; ``reference [k, W, 3]``: each target
    point's reference curve [m]; ``trace [P, k, 3]`` the target points' executed positions at every
    recorded sub-step [m]; ``sites [k]`` their site ids."""

    model: object
    qpos: np.ndarray
    time: np.ndarray
    sub: np.ndarray
    progress: np.ndarray
    deviation: np.ndarray
    ball: np.ndarray
    ball_world: np.ndarray | None
    reference: np.ndarray
    trace: np.ndarray
    sites: np.ndarray
    title: str


def check_video_file(file: str | os.PathLike) -> FsPath:
    """``file`` as a path if its suffix is one :func:`write_video` writes, else :class:`RenderError`."""
    path = FsPath(file)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise RenderError(f"video file {path}: the name must end in {' / '.join(VIDEO_SUFFIXES)}")
    return path


def _render_robot(env, robot):
    """The robot whose model is drawn: an MJX executor's (the whole simulated robot), else ``robot``."""
    return getattr(env.executor, "robot", None) or robot


def _joint_map(env, ro: E.Rollout, render) -> np.ndarray:
    """``qpos`` addresses in the rendered model of the joints whose positions ``ro.executed`` holds."""
    n = ro.executed.shape[-1]
    active = getattr(env.executor, "active", None)
    adr = np.asarray(render.qpos_adr)
    if active is not None:
        return adr[np.asarray(active)]
    if len(adr) != n:
        raise RenderError(f"cannot place the {n} executed joints in {render.name}'s {len(adr)} joints")
    return adr


def episode_scene(env, ro: E.Rollout, robot, b: int, settings: VideoSettings = VideoSettings(),
                  measure: list | None = None, title: str = "") -> EpisodeScene:
    """Gather what the frames of episode ``b`` of ``ro`` show (see :class:`EpisodeScene`).

    ``robot``: the evaluated :class:`~mjx_pathtrack.robots.registry.Robot` (the FK robot of
    :func:`~mjx_pathtrack.evaluation.report.build_env`); ``measure``: the user's curves the
    evaluation measured against (drawn instead of the policy's reference)."""
    import mujoco

    from mjx_pathtrack.robots import registry as robots

    if not 0 <= b < ro.executed.shape[1]:
        raise RenderError(f"episode {b} is not in the rendered batch of {ro.executed.shape[1]} episodes")
    has_ball = "ball" in ro.scene
    render = robots.load_robot("iiwa_ball", dt=float(env.config.dt)) if has_ball else _render_robot(env, robot)
    model = render.mj_model
    adr = _joint_map(env, ro, render)
    dt = float(env.config.dt)
    live = np.flatnonzero(ro.live[:, b])
    steps = len(live)
    poly = E.executed_polyline(ro, b)                           # [1 + L S, n]
    substeps = (len(poly) - 1) // max(steps, 1)
    n_frames = int(np.floor(steps * dt * settings.fps + 1e-9)) + 1
    time = np.arange(n_frames) / settings.fps
    sub = np.minimum(np.rint(time / dt * max(substeps, 1)).astype(int), len(poly) - 1)  # frame -> sub-step
    # the scene at every recorded sub-step j (time j dt / S): decision step k_j, fraction into it
    t_sub = np.arange(len(poly)) * dt / max(substeps, 1)
    k = np.minimum((t_sub / dt + 1e-9).astype(int), max(steps - 1, 0))
    frac = np.clip(t_sub / dt - k, 0.0, 1.0)[:, None]

    def blend(x):  # a per-step record [T, B, ...] of episode b, linear between the ends of the steps
        x = np.asarray(x, np.float64)[live, b]
        before = np.concatenate([x[:1], x[:-1]])  # the first step starts from its own end (not recorded)
        return (1 - frac) * before[k] + frac * x[k]

    qpos = np.broadcast_to(np.asarray(render.qpos0, np.float64), (len(poly), model.nq)).copy()
    if "qpos" in ro.scene and steps:
        qpos = blend(ro.scene["qpos"])
        if render.floating:   # the base orientation: normalised linear blend of the quaternions
            qpos[:, 3:7] /= np.linalg.norm(qpos[:, 3:7], axis=1, keepdims=True)
    qpos[:, adr] = poly
    done = np.minimum(np.floor(time / dt + 1e-9).astype(int), steps)  # decision steps completed at each frame
    progress, deviation = (np.where(done > 0, np.asarray(x)[live, b][np.maximum(done - 1, 0)], 0.0) if steps else
                           np.zeros(n_frames) for x in (ro.progress, ro.deviation))
    try:
        sites = np.array([model.site(name).id for name in robot.target_sites])
    except KeyError as e:
        raise RenderError(f"{render.name}: no target site {e} to draw the tool path") from e
    data = mujoco.MjData(model)
    trace = _site_positions(model, data, qpos, sites)
    curves, counts = E.reference_curves(env, _one(ro, b), measure=measure)
    ref_qpos = np.broadcast_to(qpos[0], (int(counts[0]), model.nq)).copy()
    ref_qpos[:, adr] = curves[0, :counts[0]]
    reference = _site_positions(model, data, ref_qpos, sites).transpose(1, 0, 2)
    frames = qpos[sub]
    ball = np.full(n_frames, np.nan)
    ball_world = None
    if has_ball:
        plate = model.site("plate").id
        ball_qpos = int(model.jnt_qposadr[model.joint("ball").id])
        local = blend(ro.scene["ball"])[sub] if steps else np.zeros((n_frames, 3))
        ball = np.linalg.norm(local[:, :2], axis=1)
        ball_world = np.zeros((n_frames, 3))
        for f in range(n_frames):
            data.qpos[:] = frames[f]
            mujoco.mj_kinematics(model, data)
            ball_world[f] = data.site_xpos[plate] + data.site_xmat[plate].reshape(3, 3) @ local[f]
            frames[f, ball_qpos:ball_qpos + 7] = np.concatenate([ball_world[f], [1.0, 0.0, 0.0, 0.0]])
    return EpisodeScene(model, frames, time, sub, progress, deviation, ball, ball_world, reference, trace, sites,
                        title)


def _one(ro: E.Rollout, b: int) -> E.Rollout:
    """Episode ``b`` of ``ro`` as a batch of one (for :func:`rollout.reference_curves`)."""
    import jax

    paths = jax.tree.map(lambda x: np.asarray(x)[b:b + 1], ro.paths)
    return ro._replace(paths=paths, s_start=np.asarray(ro.s_start)[b:b + 1],
                       path_index=np.asarray(ro.path_index)[b:b + 1])


def _site_positions(model, data, qpos: np.ndarray, sites: np.ndarray) -> np.ndarray:
    """Positions ``[F, k, 3]`` [m] of ``sites`` at each row of ``qpos [F, nq]`` (MuJoCo kinematics)."""
    import mujoco

    out = np.zeros((len(qpos), len(sites), 3))
    for f, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        out[f] = data.site_xpos[sites]
    return out


def _thin(points: np.ndarray, most: int = MAX_SEGMENTS) -> np.ndarray:
    if len(points) <= most + 1:
        return points
    keep = np.unique(np.linspace(0, len(points) - 1, most + 1).round().astype(int))
    return points[keep]


def _add_polyline(scene, points: np.ndarray, width: float, rgba) -> None:
    """Line segments ``width`` px wide along ``points [P, 3]`` into the ``mujoco.MjvScene`` (as many
    as fit; lines, not capsules: a capsule costs the software renderer ~0.7 ms, a line ~0.01 ms)."""
    import mujoco

    rgba = np.asarray(rgba, np.float32)
    for p0, p1 in zip(points[:-1], points[1:]):
        if scene.ngeom >= scene.maxgeom:
            return
        if np.linalg.norm(p1 - p0) < 1e-6:
            continue
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_LINE, np.zeros(3), np.zeros(3), np.eye(3).ravel(), rgba)
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_LINE, width, p0, p1)
        scene.ngeom += 1


def _add_floor(scene, model) -> None:
    """A grey ground plane at z = 0 where the model has none (fixed-base arms)."""
    import mujoco

    if any(model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE for g in range(model.ngeom)) or \
            scene.ngeom >= scene.maxgeom:
        return
    geom = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_PLANE, np.array([1.5, 1.5, 0.05]), np.zeros(3),
                        np.eye(3).ravel(), np.array([0.55, 0.57, 0.6, 1.0], np.float32))
    scene.ngeom += 1


def _lit_model(model):
    """A copy of ``model`` with a brighter head light (the imported robots bring no lights)."""
    import copy

    lit = copy.deepcopy(model)
    lit.vis.headlight.ambient[:] = 0.35
    lit.vis.headlight.diffuse[:] = 0.6
    lit.vis.headlight.specular[:] = 0.2
    return lit


def _caption(frame: np.ndarray, lines: list[str]) -> np.ndarray:
    """``frame`` with ``lines`` written on a dark band along its bottom edge (Pillow)."""
    from PIL import Image, ImageDraw, ImageFont

    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image)
    size = max(10, frame.shape[0] // 30)
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType sizes
        font = ImageFont.load_default()
    top = frame.shape[0] - (size + 4) * len(lines) - 6
    draw.rectangle([0, top, frame.shape[1], frame.shape[0]], fill=(20, 20, 24))
    for i, line in enumerate(lines):
        draw.text((8, top + 4 + i * (size + 4)), line, fill=(235, 235, 235), font=font)
    return np.asarray(image)


def render_frames(scene: EpisodeScene, settings: VideoSettings = VideoSettings()) -> np.ndarray:
    """The frames ``[F, H, W, 3]`` (uint8) of :class:`EpisodeScene` ``scene``."""
    import mujoco

    model = _lit_model(scene.model)
    option = mujoco.MjvOption()
    option.geomgroup[:] = 1  # every group: the imported robots' only shapes (fitted primitives) are in group 3
    camera = mujoco.MjvCamera()
    # frame the drawn curves and the robot's base (the world origin of every robot here)
    points = np.concatenate([scene.reference.reshape(-1, 3), scene.trace.reshape(-1, 3), np.zeros((1, 3))])
    if scene.ball_world is not None:
        points = np.concatenate([points, scene.ball_world])
    lo, hi = points.min(axis=0), points.max(axis=0)
    camera.lookat[:] = 0.5 * (lo + hi)
    camera.distance = settings.distance or 0.6 + 1.5 * float(np.max(hi - lo))
    camera.azimuth, camera.elevation = settings.azimuth, settings.elevation
    data = mujoco.MjData(model)
    reference = [_thin(curve) for curve in scene.reference]
    segments = sum(len(c) for c in reference) + (MAX_SEGMENTS + 1) * len(scene.sites)
    try:
        renderer = mujoco.Renderer(model, settings.height, settings.width, max_geom=model.ngeom + segments + 16)
    except Exception as e:  # noqa: BLE001  (GL back ends raise their own types)
        raise RenderError(f"offscreen rendering failed ({type(e).__name__}: {e}); set MUJOCO_GL=egl (or osmesa) "
                          "before mujoco is imported") from e
    frames = np.zeros((len(scene.qpos), settings.height, settings.width, 3), np.uint8)
    try:
        for f, q in enumerate(scene.qpos):
            data.qpos[:] = q
            mujoco.mj_kinematics(model, data)
            renderer.update_scene(data, camera, option)
            _add_floor(renderer.scene, model)
            for curve in reference:
                _add_polyline(renderer.scene, curve, settings.line_width, REFERENCE_RGBA)
            for i in range(len(scene.sites)):
                _add_polyline(renderer.scene, _thin(scene.trace[:scene.sub[f] + 1, i]), settings.line_width + 1,
                              TRACE_RGBA)
            lines = [f"t {scene.time[f]:5.2f} s   progress {100 * scene.progress[f]:5.1f} %   "
                     f"deviation {scene.deviation[f]:.3f} rad"
                     + (f"   ball {100 * scene.ball[f]:4.1f} cm from centre" if np.isfinite(scene.ball[f]) else "")]
            legend = "blue: reference tool path, orange: executed"
            frames[f] = _caption(renderer.render(), [f"{scene.title}   ({legend})" if scene.title else legend] + lines)
    finally:
        renderer.close()
    return frames


def write_video(file: str | os.PathLike, frames: np.ndarray, fps: int) -> FsPath:
    """Write ``frames [F, H, W, 3]`` (uint8) to ``file``: ``.mp4`` (H.264, ``imageio-ffmpeg``),
    ``.gif`` (Pillow) or ``.png`` (the last frame). Atomic: no partial file is left behind."""
    path = check_video_file(file)
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
        raise RenderError(f"frames must have shape [F >= 1, H, W, 3], got {frames.shape}")
    suffix = path.suffix.lower()
    from PIL import Image

    if suffix == ".png":
        buf = io.BytesIO()
        Image.fromarray(frames[-1]).save(buf, format="PNG")
        atomic_write_bytes(path, buf.getvalue())
    elif suffix == ".gif":
        buf = io.BytesIO()
        images = [Image.fromarray(f) for f in frames]
        images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=1000.0 / fps, loop=0)
        atomic_write_bytes(path, buf.getvalue())
    else:
        import tempfile

        import imageio_ffmpeg

        height, width = frames.shape[1:3]
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".mp4", dir=path.parent)
        os.close(fd)
        try:
            with warnings.catch_warnings():  # the ffmpeg child is started with fork + exec: nothing of JAX runs in it
                warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
                writer = imageio_ffmpeg.write_frames(tmp, (width, height), fps=fps, codec="libx264", pix_fmt_in="rgb24",
                                                     pix_fmt_out="yuv420p", macro_block_size=1, quality=7)
                writer.send(None)
            for frame in frames:
                writer.send(np.ascontiguousarray(frame))
            writer.close()
            atomic_write(path, lambda f: f.write(FsPath(tmp).read_bytes()))
        finally:
            FsPath(tmp).unlink(missing_ok=True)
    return path


def write_episode_video(file: str | os.PathLike, env, ro: E.Rollout, robot, b: int,
                        settings: VideoSettings = VideoSettings(), measure: list | None = None,
                        title: str = "") -> FsPath:
    """Render episode ``b`` of the recorded batch ``ro`` (:func:`episode_scene`,
    :func:`render_frames`) and write it to ``file`` (:func:`write_video`); returns the file."""
    check_video_file(file)
    scene = episode_scene(env, ro, robot, b, settings, measure, title)
    return write_video(file, render_frames(scene, settings), settings.fps)
