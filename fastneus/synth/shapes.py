"""Built-in test shapes for synthetic scenes (trimesh meshes, world units = metres).

Every shape is a set of closed, non-interpenetrating parts, so each ground-truth surface
point is a real outer surface. :func:`normalise_mesh` centres a mesh and scales it to
a bounding-sphere radius of 1 m (about 2 m across, like NeRF-Synthetic).
"""
from __future__ import annotations

import numpy as np
import trimesh

from fastneus.errors import FastneusError

SHAPES = ("sphere", "torus", "toy", "rock", "ant", "airplane", "hexnut")


def _coloured(m: trimesh.Trimesh, rgb) -> trimesh.Trimesh:
    m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=np.tile(np.r_[rgb, 255], (len(m.vertices), 1)))
    return m


def _place(m: trimesh.Trimesh, translate=(0, 0, 0), rotate_deg=0.0, axis=(1, 0, 0)) -> trimesh.Trimesh:
    T = trimesh.transformations.rotation_matrix(np.deg2rad(rotate_deg), axis)
    T[:3, 3] = translate
    m.apply_transform(T)
    return m


def toy_parts() -> list[trimesh.Trimesh]:
    """Parts of the composite ``toy``: a thick-walled cup (concavity), a thin fin (2 cm),
    a standing torus (hole) and a sphere, laid out with disjoint bounding boxes."""
    # cup: revolve a closed profile (r, z) around z; opening faces up (+z) toward the cameras
    prof = np.array([(0, 0), (0.45, 0), (0.5, 0.05), (0.5, 0.65), (0.42, 0.65), (0.42, 0.08), (0, 0.08)])
    cup = _coloured(trimesh.creation.revolve(prof, sections=96), (200, 120, 60))
    _place(cup, (-0.55, 0.25, -0.45))
    fin = _coloured(trimesh.creation.box((0.7, 0.02, 0.5)), (60, 160, 200))
    _place(fin, (0.55, 0.55, -0.15), rotate_deg=20, axis=(0, 0, 1))
    torus = _coloured(trimesh.creation.torus(major_radius=0.32, minor_radius=0.09, major_sections=96,
                                             minor_sections=32), (180, 60, 160))
    _place(torus, (0.45, -0.45, -0.1), rotate_deg=90, axis=(1, 0, 0))  # standing, hole facing -y
    ball = _coloured(trimesh.creation.icosphere(subdivisions=4, radius=0.25), (120, 200, 90))
    _place(ball, (-0.45, -0.55, -0.2))
    return [cup, fin, torus, ball]


def rock(seed: int = 3) -> trimesh.Trimesh:
    """A scanned-stone-like closed surface: an icosphere displaced radially by ridged noise.

    Random Fourier features (smooth on the sphere) give the broad lumps, their absolute values
    (ridged) the creases; the result is star-shaped, so it is closed and never self-intersects.
    """
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    v = np.asarray(m.vertices)
    disp = np.zeros(len(v))
    for octave, (n, freq, amp, ridged) in enumerate(((6, 1.5, 0.22, False), (12, 3.5, 0.10, True),
                                                      (24, 8.0, 0.03, True))):
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        phase = rng.uniform(0, 2 * np.pi, n)
        w = np.sin(freq * v @ d.T + phase) / np.sqrt(n)
        layer = (1.0 - 2.0 * np.abs(w)) if ridged else w
        disp += amp * layer.sum(1)
    r = 1.0 + disp - disp.mean()
    m.vertices = v * np.clip(r, 0.5, None)[:, None] * np.array([1.0, 0.8, 0.65])  # a flattish stone
    return _coloured(m, (150, 140, 125))


def _segment(a, b, radius: float, sections: int = 16) -> trimesh.Trimesh:
    """A closed cylinder from point ``a`` to point ``b``."""
    return trimesh.creation.cylinder(radius=radius, segment=np.array([a, b], dtype=np.float64), sections=sections)


def ant() -> trimesh.Trimesh:
    """An ant-like shape: head, thorax and abdomen (ellipsoids) and six thin two-segment legs
    (4 cm thick for a 2.6 m body: about a pixel in an 800-px view) that stop short of the body."""
    def ellipsoid(c, r):
        m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        m.vertices = m.vertices * np.asarray(r) + np.asarray(c)
        return m

    parts = [ellipsoid((-0.95, 0, 0.35), (0.25, 0.2, 0.2)), ellipsoid((-0.3, 0, 0.35), (0.3, 0.16, 0.16)),
             ellipsoid((0.55, 0, 0.4), (0.5, 0.32, 0.3))]
    for x in (-0.45, -0.3, -0.15):
        for side in (-1, 1):
            hip = np.array([x, side * 0.2, 0.33])      # just outside the thorax (no interpenetration)
            knee = np.array([x + 2.2 * (x + 0.3), side * 0.6, 0.55])
            foot = np.array([x + 4.0 * (x + 0.3), side * 0.95, -0.1])
            parts += [_segment(hip, knee, 0.02), _segment(knee + (knee - hip) / np.linalg.norm(knee - hip) * 0.045,
                                                          foot, 0.02)]
    return _coloured(trimesh.util.concatenate(parts), (110, 70, 45))


def airplane() -> trimesh.Trimesh:
    """An airplane-like shape: a capsule fuselage, two thin wings (3 cm), a tailplane and a fin,
    each a separate closed part beside the fuselage."""
    fus = trimesh.creation.capsule(height=2.0, radius=0.16, count=[24, 24])
    _place(fus, (0, 0, 0), rotate_deg=90, axis=(0, 1, 0))  # along x
    parts = [fus]
    for side in (-1, 1):
        wing = trimesh.creation.box((0.45, 1.1, 0.03))
        _place(wing, (0.05, side * (0.17 + 0.56), 0.0), rotate_deg=side * 4, axis=(1, 0, 0))
        tail = trimesh.creation.box((0.22, 0.35, 0.025))
        _place(tail, (-0.95, side * (0.17 + 0.175), 0.05))
        parts += [wing, tail]
    fin = trimesh.creation.box((0.3, 0.025, 0.35))
    _place(fin, (-0.95, 0.0, 0.17 + 0.175))
    return _coloured(trimesh.util.concatenate(parts), (200, 200, 210))


def hexnut(outer: float = 1.0, hole: float = 0.5, height: float = 0.6, n: int = 96) -> trimesh.Trimesh:
    """A hexagonal nut: a hexagonal prism (circumradius ``outer``) with a round hole through it.

    Both walls are sampled at the same ``n`` angles (a multiple of 6, so the hexagon's corners
    are vertices) and joined by annular caps: one closed, watertight surface of genus 1.
    """
    th = np.arange(n) * 2 * np.pi / n
    apothem = outer * np.cos(np.pi / 6)
    r_hex = apothem / np.cos((th % (np.pi / 3)) - np.pi / 6)
    ring = lambda r, z: np.c_[r * np.cos(th), r * np.sin(th), np.full(n, z)]  # noqa: E731
    v = np.concatenate([ring(r_hex, height / 2), ring(np.full(n, hole), height / 2),
                        ring(r_hex, -height / 2), ring(np.full(n, hole), -height / 2)])
    to, ti, bo, bi = (np.arange(n) + k * n for k in range(4))
    nx = lambda a: np.roll(a, -1)  # noqa: E731
    f = []
    for a, b, c, d in ((to, nx(to), nx(ti), ti), (bo, bi, nx(bi), nx(bo)),   # caps (top up, bottom down)
                       (bo, nx(bo), nx(to), to), (bi, ti, nx(ti), nx(bi))):  # outer wall, hole wall
        f += [np.c_[a, b, c], np.c_[a, c, d]]
    m = trimesh.Trimesh(v, np.concatenate(f), process=True)
    trimesh.repair.fix_normals(m)
    return _place(_coloured(m, (170, 165, 150)), rotate_deg=35)


def make_shape(name: str) -> trimesh.Trimesh:
    """A built-in shape (before normalisation) with per-vertex colours."""
    if name == "sphere":
        # finely tessellated: max radial deviation ~5e-5 of the radius
        return _coloured(trimesh.creation.icosphere(subdivisions=6, radius=1.0), (180, 180, 180))
    if name == "torus":
        m = trimesh.creation.torus(major_radius=0.7, minor_radius=0.3, major_sections=128, minor_sections=64)
        return _place(_coloured(m, (190, 150, 110)), rotate_deg=30)
    if name == "toy":
        parts = toy_parts()
        return trimesh.util.concatenate(parts)
    if name == "rock":
        return rock()
    if name == "ant":
        return ant()
    if name == "airplane":
        return airplane()
    if name == "hexnut":
        return hexnut()
    raise FastneusError(f"unknown shape {name!r}; use one of {', '.join(SHAPES)}", field="--shape")


def load_mesh(path) -> trimesh.Trimesh:
    """Load any mesh trimesh reads (PLY/OBJ/STL/GLB...), scenes flattened into one mesh."""
    try:
        m = trimesh.load(str(path), force="mesh", process=True)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
        raise FastneusError(f"cannot load mesh: {e}", file=path, field="--mesh") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise FastneusError("no triangles in the mesh", file=path, field="--mesh")
    return m


def normalise_mesh(m: trimesh.Trimesh, radius: float = 1.0) -> tuple[trimesh.Trimesh, float, np.ndarray]:
    """Centre the bounding box at the origin and scale to bounding-sphere ``radius``.

    Returns:
        (mesh, scale, offset) with ``x_new = scale * (x_old + offset)``.
    """
    m = m.copy()
    offset = -m.bounds.mean(axis=0)
    m.apply_translation(offset)
    r = float(np.linalg.norm(m.vertices, axis=1).max())
    if not np.isfinite(r) or r <= 0:
        raise FastneusError("degenerate mesh (zero size)", field="--mesh")
    scale = radius / r
    m.apply_scale(scale)
    return m, scale, offset
