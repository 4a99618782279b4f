"""Procedural free-form objects laser-scanned in pairs for benchmarks/scan_sim.py: what laser
scans of small objects look like (an isolated object, no table, smooth curved surfaces, turntable
or hand-held views, dense, mixed pixels at the silhouette), unlike the fused tabletop chunk of
`_scan_sim_object.py`.

Shapes (:data:`SHAPES`), each scaled so that its bounding box's longest side is the asked size:

* ``blob``: a sphere whose radius along each direction is ``1 + sum c_k m_k(u)``, ``m_k`` the
  monomials of degree 1 to 4 of the unit direction ``u`` (the span of the spherical harmonics
  up to degree 4), stretched into an ellipsoid;
* ``superquadric``: ``|x/a|^(2/e) + |y/b|^(2/e) + |z/c|^(2/e) = 1`` (rounded boxes to pinched
  shapes), its radius deformed a little as a blob's;
* ``torus``: a ring of two radii, bent out of its plane by a low-order wave;
* ``blobs``: two to four deformed ellipsoids that overlap (a union: ray casting sees only the
  outside).

A pair is two views of one object by a pinhole laser scanner (rays ``size / resolution`` apart
at the object): ``turntable`` views at one elevation, ``angle_deg`` apart in azimuth about the
object's vertical axis; ``handheld`` views also differ in elevation (up to 20 deg) and roll of
the scanner, and in distance (up to 15 %). Range noise grows with the incidence angle
(``noise / cos``, capped at 5x); at a depth discontinuity (a neighbour ray misses or hits more
than ``JUMP`` of the size farther) a share of the returns are mixed pixels: the range moves
towards the far side (a missing neighbour: up to ``TRAIL`` of the size behind), as a laser
spot that straddles the edge reports. ``outliers``: a share of all the returns (anywhere on
the object) lie off the surface along their ray, up to ``TRAIL`` of the size in front or
behind (spurious returns, multipath).
"""

from __future__ import annotations

import math
from itertools import combinations_with_replacement

import numpy as np

from _scan_sim_geometry import cast_full, quiet_open3d, raycasting_scene, relative
from _scan_sim_object import look_at, pinhole_directions

SHAPES = ("blob", "superquadric", "torus", "blobs")
VIEWS = ("turntable", "handheld")
#: mixed pixels: a neighbour farther than this share of the size makes a depth discontinuity
JUMP = 0.02
#: ... and a return next to a miss trails up to this share of the size behind the edge
TRAIL = 0.15
#: share of the returns at a discontinuity that are mixed
MIXED_SHARE = 0.5
#: the scanner's distance in object sizes
DISTANCE = 3.0


def _sphere(subdivisions: int = 5):
    """A unit icosphere (legacy open3d mesh, about 10k vertices at 5 subdivisions)."""
    o3d = quiet_open3d()
    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0)
    mesh = mesh.subdivide_loop(subdivisions)
    v = np.asarray(mesh.vertices)
    mesh.vertices = o3d.utility.Vector3dVector(v / np.linalg.norm(v, axis=1, keepdims=True))
    return mesh


def _monomials(u: np.ndarray, degree: int = 4) -> np.ndarray:
    """``(N, K)`` the monomials of degree 1 to ``degree`` of ``u (N, 3)``."""
    cols = []
    for d in range(1, degree + 1):
        for combo in combinations_with_replacement(range(3), d):
            cols.append(np.prod(u[:, list(combo)], axis=1))
    return np.stack(cols, axis=1)


def _deformation(u: np.ndarray, rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """``(N,)`` a smooth random factor about 1 over unit directions ``u (N, 3)`` (peak
    deviation ``amplitude``)."""
    m = _monomials(u)
    c = rng.standard_normal(m.shape[1])
    f = m @ c
    f -= f.mean()
    return 1.0 + amplitude * f / max(np.abs(f).max(), 1e-12)


def _bumps(u: np.ndarray, rng: np.random.Generator, count: int, amplitude: float) -> np.ndarray:
    """``(N,)`` a factor about 1 over unit directions ``u (N, 3)``: ``count`` gaussian bumps
    and dents (angular widths 0.12 to 0.35 rad, heights up to ``amplitude``) at random
    directions: the detail that tells one side of a smooth object from another."""
    ways = rng.standard_normal((count, 3))
    ways /= np.linalg.norm(ways, axis=1, keepdims=True)
    width = rng.uniform(0.12, 0.35, count)
    height = amplitude * rng.uniform(0.3, 1.0, count) * rng.choice([-1.0, 1.0], count)
    angle = np.arccos(np.clip(u @ ways.T, -1.0, 1.0))  # (N, count)
    return 1.0 + np.sum(height * np.exp(-0.5 * (angle / width) ** 2), axis=1)


def _with_vertices(mesh, vertices: np.ndarray):
    o3d = quiet_open3d()
    out = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(np.asarray(mesh.triangles))
    )
    return out


def _blob(rng: np.random.Generator, amplitude: float = 0.3, bumps: int = 10):
    sphere = _sphere()
    u = np.asarray(sphere.vertices)
    axes = rng.uniform(0.6, 1.0, 3)
    radius = _deformation(u, rng, amplitude) * _bumps(u, rng, bumps, 0.12)
    return _with_vertices(sphere, u * radius[:, None] * axes)


def _superquadric(rng: np.random.Generator):
    sphere = _sphere()
    u = np.asarray(sphere.vertices)
    e = rng.uniform(0.3, 1.6)
    axes = rng.uniform(0.5, 1.0, 3)
    # the point along u where |x/a|^(2/e) + ... = 1
    s = np.sum(np.abs(u / axes) ** (2 / e), axis=1) ** (-e / 2)
    radius = s * _deformation(u, rng, 0.08) * _bumps(u, rng, 8, 0.1)
    return _with_vertices(sphere, u * radius[:, None])


def _torus(rng: np.random.Generator):
    o3d = quiet_open3d()
    ring = rng.uniform(0.25, 0.45)
    mesh = o3d.geometry.TriangleMesh.create_torus(1.0, ring, 160, 60)
    v = np.asarray(mesh.vertices).copy()
    phase, k = rng.uniform(0, 2 * np.pi), rng.integers(1, 3)
    v[:, 2] += rng.uniform(0.1, 0.35) * np.cos(k * np.arctan2(v[:, 1], v[:, 0]) + phase)
    v[:, 1] *= rng.uniform(0.7, 1.0)
    ways = rng.standard_normal((8, 3)) * [1.0, 1.0, 0.2]  # bumps on the tube, about the ring
    ways /= np.linalg.norm(ways, axis=1, keepdims=True)
    near = np.exp(-0.5 * (np.linalg.norm(v[:, None] - ways, axis=2) / 0.25) ** 2)  # (N, 8)
    height = ring * rng.uniform(-0.4, 0.4, 8)
    centre = v.copy()
    centre[:, 2] = 0.0
    centre *= 1.0 / np.maximum(np.linalg.norm(centre, axis=1, keepdims=True), 1e-9)
    out = v - centre  # from the tube's axis (about)
    out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-9)
    return _with_vertices(mesh, v + (near @ height)[:, None] * out)


def _blobs(rng: np.random.Generator):
    o3d = quiet_open3d()
    mesh = o3d.geometry.TriangleMesh()
    for _ in range(rng.integers(2, 5)):
        part = _blob(rng, 0.2, bumps=4)
        scale = rng.uniform(0.4, 0.8)
        v = np.asarray(part.vertices) * scale + rng.uniform(-0.55, 0.55, 3)
        mesh += _with_vertices(part, v)
    return mesh


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random ``(3, 3)`` rotation (of a normalised gaussian quaternion)."""
    w, x, y, z = rng.standard_normal(4) / 1.0
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def shape_mesh(kind: str, size: float, seed: int):
    """A legacy open3d mesh of shape ``kind`` (:data:`SHAPES`), randomly turned, centred,
    scaled to a bounding box of longest side ``size`` m."""
    rng = np.random.default_rng([seed, 7, SHAPES.index(kind)])
    mesh = {"blob": _blob, "superquadric": _superquadric, "torus": _torus, "blobs": _blobs}[kind](
        rng
    )
    v = np.asarray(mesh.vertices) @ _random_rotation(rng).T
    lo, hi = v.min(0), v.max(0)
    v = (v - (lo + hi) / 2) * (size / float(np.max(hi - lo)))
    return _with_vertices(mesh, v)


def _scanner_poses(view: str, angle_deg: float, rng: np.random.Generator, size: float):
    """``T_world_scanner (4, 4)`` of the two views, looking at the object at the origin."""
    elevation = np.radians(rng.uniform(10, 40))
    azimuth = rng.uniform(0, 2 * np.pi)
    poses = []
    for k in (0, 1):
        a = azimuth + k * np.radians(angle_deg)
        e, dist, roll = elevation, DISTANCE * size, 0.0
        if view == "handheld" and k == 1:
            e += np.radians(rng.uniform(-20, 20))
            dist *= rng.uniform(0.85, 1.15)
            roll = np.radians(rng.uniform(-30, 30))
        eye = dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        aim = rng.normal(0, 0.03 * size, 3)  # not quite at the centre
        T = look_at(eye, aim)
        c, s = np.cos(roll), np.sin(roll)
        T[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        poses.append(T)
    return poses


def laser_scan(scene, T_world_scanner, size, resolution, noise, rng, outliers=0.0):
    """``(N, 3)`` returns in the scanner's frame: a square pinhole grid covering the object,
    rays ``size / resolution`` apart at the object, range noise ``noise / cos(incidence)``
    (capped at 5x), mixed pixels at the silhouette, a share ``outliers`` of the returns off
    the surface along their ray."""
    dist = float(np.linalg.norm(T_world_scanner[:3, 3]))
    half_fov = np.degrees(np.arctan(0.8 * size / dist))
    dirs = pinhole_directions(half_fov, size / resolution / dist)
    side = math.isqrt(len(dirs))  # a square grid
    world = dirs @ T_world_scanner[:3, :3].T
    t, normals = cast_full(scene, T_world_scanner[:3, 3], world)
    cos = np.abs(np.sum(normals * world, axis=1))
    hit = np.isfinite(t)
    ranges = t + noise * np.minimum(1 / np.maximum(cos, 1e-3), 5.0) * rng.standard_normal(len(t))
    depth = np.where(hit, t, np.inf).reshape(side, side)
    # the farthest of the 4 neighbours (inf: a miss)
    pad = np.pad(depth, 1, constant_values=np.inf)
    with np.errstate(invalid="ignore"):  # inf - inf: a miss next to a miss
        far = np.max(
            np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]]), axis=0
        ).ravel()
        edge = hit & (far - t > JUMP * size)
        behind = np.where(np.isfinite(far), far - t, TRAIL * size)
    mixed = edge & (rng.random(len(t)) < MIXED_SHARE)
    ranges[mixed] = t[mixed] + rng.random(int(mixed.sum())) * behind[mixed]
    if outliers > 0:  # drawn only when asked: the scans without them stay as they were
        stray = hit & (rng.random(len(t)) < outliers)
        ranges[stray] = t[stray] + rng.uniform(-TRAIL, TRAIL, int(stray.sum())) * size
    return dirs[hit] * ranges[hit, None]


def shape_pair(
    kind: str = "blob",
    angle_deg: float = 40.0,
    size: float = 0.2,
    view: str = "turntable",
    resolution: float = 400.0,
    noise: float = 1e-4,
    seed: int = 0,
    outliers: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two laser scans of one free-form object (:func:`shape_mesh`) and the truth; a share
    ``outliers`` of each scan's returns off the surface (:func:`laser_scan`).

    Returns:
        ``(src (N, 3), tgt (M, 3), T_gt (4, 4))`` float64: each scan in its scanner's frame
        (z forward, y down, metres) and the transform mapping src's frame into tgt's.
    """
    mesh = shape_mesh(kind, size, seed)
    scene = raycasting_scene(mesh)
    rng = np.random.default_rng([seed, 8, SHAPES.index(kind), VIEWS.index(view)])
    poses = _scanner_poses(view, angle_deg, rng, size)
    src, tgt = (laser_scan(scene, T, size, resolution, noise, rng, outliers) for T in poses)
    return src, tgt, relative(poses[0], poses[1])
