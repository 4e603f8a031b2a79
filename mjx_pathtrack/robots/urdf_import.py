"""URDF (parsed with yourdfpy) -> MuJoCo ``MjSpec``, written by this project.

What the conversion does:

* one MuJoCo body per URDF link; fixed joints become joint-less child bodies, which the
  compiler fuses into their parent (``fusestatic``) so MJX sees few bodies;
* revolute/continuous joints -> hinges, prismatic -> slides; joint-limit constraints are *off*
  (``limited = false``): the safe action space keeps joints inside their limits, and limit
  constraints would make the batched MJX solver ~45x slower. The URDF limits are returned in
  :class:`UrdfJoint` for :class:`~mjx_pathtrack.core.limits.JointLimits`;
* inertials are copied (``fullinertia``); link masses below ``MIN_MASS`` are bounded;
* collision geometry: boxes, cylinders and spheres are copied; meshes are replaced by a fitted
  primitive (a capsule for elongated meshes, otherwise a box) from the mesh's oriented bounding
  box (trimesh), so MJX never handles meshes. Visual elements are not converted.
* all geoms get ``contype = conaffinity = 0``; scenes switch contacts on where they need them.

Lengths in m, angles in rad, masses in kg.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import io
import re
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

#: smallest body mass [kg] / inertia [kg m^2] given to links (URDF dummy links have ~0)
MIN_MASS = 1e-3
MIN_INERTIA = 1e-6
#: a mesh whose longest OBB extent is at least this many times its second becomes a capsule
CAPSULE_ASPECT = 1.6

_NUMERIC_ATTR = re.compile(r'(\b(?:rpy|xyz|scale)=")([^"]*)"')


@dataclasses.dataclass(frozen=True)
class UrdfJoint:
    """A movable URDF joint: name, type (``revolute``/``continuous``/``prismatic``), limits
    (``lower``/``upper`` in rad or m, ``-inf``/``inf`` if continuous; ``velocity`` in rad/s or m/s)."""

    name: str
    type: str
    lower: float
    upper: float
    velocity: float


def load_urdf(source: str | Path):
    """Parse a URDF file with yourdfpy, without loading meshes.

    Commas inside ``xyz``/``rpy``/``scale`` attributes (a typo in the ``armar`` URDFs) are
    read as separators. Raises ``FileNotFoundError`` for a missing file and ``ValueError``
    naming the file for anything yourdfpy or the XML parser cannot read.
    """
    import yourdfpy

    path = Path(source)
    if not path.is_file():
        raise FileNotFoundError(f"URDF file not found: {path}")
    text = _NUMERIC_ATTR.sub(lambda m: m.group(1) + m.group(2).replace(",", " ") + '"', path.read_text())
    try:
        urdf = yourdfpy.URDF.load(io.StringIO(text), load_meshes=False, build_scene_graph=False)
    except Exception as exc:  # lxml, float() and yourdfpy errors: all mean "malformed"
        raise ValueError(f"malformed URDF {path}: {type(exc).__name__}: {exc}") from exc
    robot = urdf.robot
    if not robot.links:
        raise ValueError(f"malformed URDF {path}: no links")
    names = {link.name for link in robot.links}
    for joint in robot.joints:
        for end in (joint.parent, joint.child):
            if end not in names:
                raise ValueError(f"malformed URDF {path}: joint {joint.name!r} refers to unknown link {end!r}")
        if joint.type in ("revolute", "prismatic") and joint.limit is None:
            raise ValueError(f"malformed URDF {path}: {joint.type} joint {joint.name!r} has no <limit>")
        if joint.type not in ("fixed", "revolute", "continuous", "prismatic"):
            raise ValueError(f"URDF {path}: joint type {joint.type!r} of {joint.name!r} is not supported")
    children = [joint.child for joint in robot.joints]
    if len(set(children)) != len(children):
        raise ValueError(f"malformed URDF {path}: a link has two parent joints")
    roots = sorted(names - set(children))
    if len(roots) != 1:
        raise ValueError(f"malformed URDF {path}: expected one root link, found {roots}")
    return urdf


def root_link(urdf) -> str:
    children = {joint.child for joint in urdf.robot.joints}
    return next(link.name for link in urdf.robot.links if link.name not in children)


def _pos_quat(matrix) -> tuple[np.ndarray, np.ndarray]:
    """4x4 homogeneous transform -> (pos [3], quat [4] as w, x, y, z)."""
    matrix = np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)
    x, y, z, w = Rotation.from_matrix(matrix[:3, :3]).as_quat()
    return matrix[:3, 3].copy(), np.array([w, x, y, z])


def resolve_mesh_path(filename: str, urdf_dir: Path) -> Path:
    """``package://pkg/rest`` -> the installed Python package's directory / rest;
    ``file://`` and relative paths -> relative to the URDF's folder."""
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://"):].partition("/")
        spec = importlib.util.find_spec(package)
        if spec is None or spec.origin is None:
            raise ValueError(f"mesh {filename}: Python package {package!r} not installed")
        return Path(spec.origin).parent / rest
    if filename.startswith("file://"):
        filename = filename[len("file://"):]
    path = Path(filename)
    return path if path.is_absolute() else urdf_dir / path


def link_mesh_vertices(urdf, urdf_path: str | Path, link: str) -> np.ndarray:
    """Vertices ``[k, 3]`` [m] of all collision meshes of ``link``, in the link frame (each
    mesh's scale and collision origin applied); ``ValueError`` if the link has none on disk."""
    import trimesh

    if link not in urdf.link_map:
        raise ValueError(f"link {link!r} not in the URDF {urdf_path}")
    parts = []
    for collision in urdf.link_map[link].collisions:
        mesh = collision.geometry.mesh
        if mesh is None:
            continue
        path = resolve_mesh_path(mesh.filename, Path(urdf_path).parent)
        if not path.is_file():
            continue
        scale = np.ones(3) if mesh.scale is None else np.broadcast_to(np.asarray(mesh.scale, float), (3,))
        vertices = np.asarray(trimesh.load(str(path), force="mesh").vertices, np.float64) * scale
        origin = np.eye(4) if collision.origin is None else np.asarray(collision.origin, np.float64)
        parts.append(vertices @ origin[:3, :3].T + origin[:3, 3])
    if not parts:
        raise ValueError(f"link {link!r} of {urdf_path} has no collision mesh on disk")
    return np.concatenate(parts)


@dataclasses.dataclass(frozen=True)
class Primitive:
    """A fitted collision primitive in its link frame: ``type`` ``box`` (size = half extents)
    or ``capsule`` (size = radius, half length, 0; axis = local z); pose ``pos``, ``quat`` (w, x, y, z)."""

    type: str
    size: tuple[float, float, float]
    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    far_point: tuple[float, float, float]  # end of the longest axis farthest from the link origin


@functools.lru_cache(maxsize=512)
def fit_primitive(mesh_path: str, scale: tuple[float, float, float]) -> Primitive:
    """Fit a box or capsule to a mesh file (its oriented bounding box), in the mesh frame."""
    import trimesh

    mesh = trimesh.load(mesh_path, force="mesh")
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * np.asarray(scale)
    obb = trimesh.PointCloud(vertices).bounding_box_oriented
    extents = np.asarray(obb.primitive.extents, dtype=np.float64)
    transform = np.asarray(obb.primitive.transform, dtype=np.float64)
    order = np.argsort(extents)[::-1]  # longest first
    # reorder the box axes so that the longest one is local z (capsule axis)
    axes = transform[:3, :3][:, [order[1], order[2], order[0]]]
    if np.linalg.det(axes) < 0:
        axes[:, 0] *= -1.0
    half = extents[[order[1], order[2], order[0]]] / 2.0
    center = transform[:3, 3]
    ends = [center + s * half[2] * axes[:, 2] for s in (-1.0, 1.0)]
    far = max(ends, key=lambda p: float(np.linalg.norm(p)))
    x, y, z, w = Rotation.from_matrix(axes).as_quat()
    if extents[order[0]] >= CAPSULE_ASPECT * extents[order[1]]:
        radius = float(max(half[0], half[1]))
        size = (radius, float(max(half[2] - radius, 1e-4)), 0.0)
        kind = "capsule"
    else:
        size = tuple(float(h) for h in np.maximum(half, 1e-4))
        kind = "box"
    return Primitive(kind, size, tuple(center), (w, x, y, z), tuple(far))


def _compose(matrix, prim: Primitive) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose and far point of a primitive fitted in mesh frame, expressed in the link frame."""
    matrix = np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)
    w, x, y, z = prim.quat
    rot = matrix[:3, :3] @ Rotation.from_quat([x, y, z, w]).as_matrix()
    pos = matrix[:3, :3] @ np.asarray(prim.pos) + matrix[:3, 3]
    far = matrix[:3, :3] @ np.asarray(prim.far_point) + matrix[:3, 3]
    qx, qy, qz, qw = Rotation.from_matrix(rot).as_quat()
    return pos, np.array([qw, qx, qy, qz]), far


@dataclasses.dataclass
class ConversionResult:
    """``spec``: the MjSpec (not compiled); ``joints``: movable joints in tree order;
    ``far_points``: per link, the far end of its fitted mesh primitive (link frame, m)."""

    spec: mujoco.MjSpec
    joints: list[UrdfJoint]
    far_points: dict[str, np.ndarray]


def urdf_to_spec(urdf, urdf_path: str | Path, *, fixed_joints: frozenset[str] = frozenset(),
                 floating: bool = False, base_pos=(0.0, 0.0, 0.0), damping: float | None = None,
                 armature: float = 0.0) -> ConversionResult:
    """Build an MjSpec from a parsed URDF.

    ``fixed_joints``: names of movable URDF joints to weld (e.g. ARMAR-4's legs); ``floating``:
    give the root body a free joint; ``base_pos`` [m]: root body position; ``damping``
    [N m s/rad] overrides the URDF joint damping; ``armature`` [kg m^2] added to every joint.
    """
    urdf_dir = Path(urdf_path).parent
    spec = mujoco.MjSpec()
    spec.compiler.fusestatic = True
    spec.compiler.balanceinertia = True
    spec.compiler.boundmass = MIN_MASS
    spec.compiler.boundinertia = MIN_INERTIA
    # masses come from <inertial> only (geoms are fitted boxes, not solid parts)
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    links = {link.name: link for link in urdf.robot.links}
    child_joints: dict[str, list] = {}
    for joint in urdf.robot.joints:
        child_joints.setdefault(joint.parent, []).append(joint)
    unknown = set(fixed_joints) - {j.name for j in urdf.robot.joints}
    if unknown:
        raise ValueError(f"fixed_joints names not in the URDF: {sorted(unknown)}")
    movable: list[UrdfJoint] = []
    far_points: dict[str, np.ndarray] = {}

    def add_link(body, link) -> None:
        body.name = "urdf_world" if link.name == "world" else link.name  # MuJoCo reserves "world"
        inertial = link.inertial
        if inertial is not None and inertial.mass is not None:
            pos, quat = _pos_quat(inertial.origin)
            body.explicitinertial = True
            body.mass = max(float(inertial.mass), MIN_MASS)
            body.ipos, body.iquat = pos, quat
            i = _positive_inertia(inertial.inertia)
            body.fullinertia = [i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]
        for k, collision in enumerate(link.collisions):
            _add_collision_geom(body, link.name, k, collision, urdf_dir, far_points)
        for joint in child_joints.get(link.name, []):
            pos, quat = _pos_quat(joint.origin)
            child = body.add_body(pos=pos, quat=quat)
            if joint.type != "fixed" and joint.name not in fixed_joints:
                movable.append(_add_joint(child, joint, damping, armature))
            add_link(child, links[joint.child])

    root = spec.worldbody.add_body(pos=list(base_pos))
    if floating:
        root.add_freejoint(name="floating_base")
    add_link(root, links[root_link(urdf)])
    return ConversionResult(spec, movable, far_points)


def _positive_inertia(inertia) -> np.ndarray:
    """Symmetric inertia matrix [kg m^2] with eigenvalues raised to at least ``MIN_INERTIA``
    (some URDF links have singular or indefinite inertias); ``balanceinertia`` fixes the
    triangle inequality at compile time."""
    i = np.asarray(inertia, dtype=np.float64)
    i = 0.5 * (i + i.T)
    w, v = np.linalg.eigh(i)
    return (v * np.maximum(w, MIN_INERTIA)) @ v.T


def _add_joint(body, joint, damping: float | None, armature: float) -> UrdfJoint:
    if joint.mimic is not None:
        raise ValueError(f"mimic joint {joint.name!r} is not supported")
    axis = np.asarray(joint.axis if joint.axis is not None else (1.0, 0.0, 0.0), dtype=np.float64)
    urdf_damping = joint.dynamics.damping if joint.dynamics is not None and joint.dynamics.damping else 0.0
    limit = joint.limit
    if joint.type == "continuous":
        lower, upper = -np.inf, np.inf
    else:
        lower, upper = float(limit.lower), float(limit.upper)
    velocity = float(limit.velocity) if limit is not None and limit.velocity else np.nan
    kind = mujoco.mjtJoint.mjJNT_SLIDE if joint.type == "prismatic" else mujoco.mjtJoint.mjJNT_HINGE
    body.add_joint(name=joint.name, type=kind, axis=axis / np.linalg.norm(axis),
                   limited=mujoco.mjtLimited.mjLIMITED_FALSE,
                   damping=float(urdf_damping if damping is None else damping), armature=armature)
    return UrdfJoint(joint.name, joint.type, lower, upper, velocity)


def _add_collision_geom(body, link_name: str, k: int, collision, urdf_dir: Path, far_points: dict) -> None:
    geometry = collision.geometry
    name = f"{link_name}_col{k}"
    common = dict(name=name, contype=0, conaffinity=0, group=3)
    if geometry.mesh is not None:
        path = resolve_mesh_path(geometry.mesh.filename, urdf_dir)
        if not path.is_file():  # some armar meshes are missing from the package: no geom
            return
        scale = geometry.mesh.scale
        scale = (1.0, 1.0, 1.0) if scale is None else tuple(np.broadcast_to(np.asarray(scale, float), (3,)))
        prim = fit_primitive(str(path), scale)
        pos, quat, far = _compose(collision.origin, prim)
        far_points[link_name] = far
        kind = mujoco.mjtGeom.mjGEOM_CAPSULE if prim.type == "capsule" else mujoco.mjtGeom.mjGEOM_BOX
        body.add_geom(type=kind, size=list(prim.size), pos=pos, quat=quat, **common)
        return
    pos, quat = _pos_quat(collision.origin)
    sizes = [geometry.box.size if geometry.box is not None else None,
             [geometry.cylinder.radius, geometry.cylinder.length] if geometry.cylinder is not None else None,
             [geometry.sphere.radius] if geometry.sphere is not None else None]
    if not any(s is not None and np.all(np.asarray(s, dtype=float) > 0) for s in sizes):
        return  # empty or degenerate (zero-size) geometry: placeholder, nothing to collide
    if geometry.box is not None:
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=list(np.asarray(geometry.box.size) / 2.0),
                      pos=pos, quat=quat, **common)
    elif geometry.cylinder is not None:
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                      size=[geometry.cylinder.radius, geometry.cylinder.length / 2.0, 0.0], pos=pos, quat=quat, **common)
    elif geometry.sphere is not None:
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[geometry.sphere.radius, 0.0, 0.0],
                      pos=pos, quat=quat, **common)
