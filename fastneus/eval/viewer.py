"""The mesh in an interactive 3D view inside report.html, self-contained and offline.

The viewer is ``<model-viewer>`` (vendored: ``fastneus/eval/vendor/``, see its README for the
version and licences), inlined as one ES module; the mesh is a GLB written here with numpy
(positions, normals, vertex colours, one matte double-sided material) and embedded as a base64
data URI. A large mesh is decimated for the page only (vertex clustering), so the embedded GLB
stays a few MB; the run's mesh.ply keeps every vertex.
"""
from __future__ import annotations

import base64
import html
import json
import struct
from importlib import resources

import numpy as np

VIEWER_VERSION = "@google/model-viewer 4.4.0"
MAX_FACES = 100_000  # ~2 MB of GLB: what the page embeds at most


# Headless Chromium drawing a report (the browser test, scripts/report_screenshot.py): as root on a
# machine without a network: no sandbox, SwiftShader's WebGL, nothing fetched in the background
HEADLESS_CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                           "--disable-background-networking", "--disable-component-update", "--disable-sync",
                           "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars",
                           "--force-device-scale-factor=1", "--enable-logging=stderr", "--v=0"]


def viewer_script() -> str:
    """The vendored model-viewer module's source text."""
    return (resources.files("fastneus.eval") / "vendor" / "model-viewer.min.js").read_text(encoding="utf-8")


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[V, 3] float32 area-weighted unit vertex normals of a triangle mesh."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def decimate(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
             colors: np.ndarray | None = None, max_faces: int = MAX_FACES) -> tuple:
    """At most ``max_faces`` faces by vertex clustering on a uniform grid.

    The vertices of a cell merge into their mean (normals re-normalised, colours averaged);
    faces that collapse or repeat are dropped, the first one's winding kept.

    Args:
        vertices: [V, 3]; faces: [F, 3]; normals: optional [V, 3]; colors: optional [V, 3|4] uint8.

    Returns:
        (vertices [V', 3] float64, faces [F', 3] int64, normals or None, colors uint8 or None); the
        inputs unchanged when already small enough.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) <= max_faces or len(v) == 0:
        return v, f, normals, colors
    lo = v.min(axis=0)
    edge = float(np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean()) or 1e-9
    cell = edge * np.sqrt(len(f) / max_faces)
    for _ in range(12):
        g = np.floor((v - lo) / cell).astype(np.int64)
        dims = g.max(axis=0) + 1
        _, inv = np.unique((g[:, 0] * dims[1] + g[:, 1]) * dims[2] + g[:, 2], return_inverse=True)
        inv = inv.reshape(-1)
        nf = inv[f]
        nf = nf[(nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 0] != nf[:, 2])]
        s = np.sort(nf, axis=1)
        n = int(inv.max()) + 1
        key = (s[:, 0] * n + s[:, 1]) * n + s[:, 2] if n < 2 ** 21 else s  # one int64 per face when it fits
        _, first = np.unique(key, axis=0, return_index=True)
        nf = nf[np.sort(first)]
        if len(nf) <= max_faces:
            break
        cell *= max(1.1, float(np.sqrt(len(nf) / max_faces)))
    n_cells = int(inv.max()) + 1
    count = np.bincount(inv, minlength=n_cells).astype(np.float64)[:, None]

    def mean(a: np.ndarray) -> np.ndarray:
        out = np.zeros((n_cells, a.shape[1]))
        np.add.at(out, inv, a)
        return out / np.maximum(count, 1)

    nv = mean(v)
    nn = nc = None
    if normals is not None:
        nn = mean(np.asarray(normals, dtype=np.float64))
        nn = (nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-12)).astype(np.float32)
    if colors is not None:
        nc = np.clip(mean(np.asarray(colors, dtype=np.float64)) + 0.5, 0, 255).astype(np.uint8)
    used = np.zeros(n_cells, bool)
    used[nf.ravel()] = True  # drop cells no face uses any more
    remap = np.cumsum(used) - 1
    return (nv[used], remap[nf], None if nn is None else nn[used], None if nc is None else nc[used])


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def glb_bytes(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
              colors: np.ndarray | None = None, rotation: np.ndarray | None = None) -> bytes:
    """A binary glTF 2.0 of one triangle mesh.

    Args:
        vertices: [V, 3] (world units; glTF reads them as metres); faces: [F, 3] counter-clockwise.
        normals: optional [V, 3] unit normals (computed from the faces when None).
        colors: optional [V, 3|4] uint8 sRGB vertex colours (stored linear, 16-bit, as glTF wants).
        rotation: optional [3, 3] applied to positions and normals (about the mesh's centre).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = vertex_normals(v, f) if normals is None else np.asarray(normals, dtype=np.float32).reshape(-1, 3)
    if rotation is not None and len(v):
        c = 0.5 * (v.min(axis=0) + v.max(axis=0))
        v = (v - c) @ np.asarray(rotation, dtype=np.float64).T + c
        n = n @ np.asarray(rotation, dtype=np.float32).T
    pos = v.astype("<f4")
    idx_type, idx = (5123, f.astype("<u2")) if len(v) < 65536 else (5125, f.astype("<u4"))
    blobs = [pos.tobytes(), n.astype("<f4").tobytes()]
    attrs = {"POSITION": 0, "NORMAL": 1}
    accessors = [
        {"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
         "min": pos.min(axis=0).tolist() if len(v) else [0, 0, 0], "max": pos.max(axis=0).tolist() if len(v) else [0, 0, 0]},
        {"bufferView": 1, "componentType": 5126, "count": len(v), "type": "VEC3"},
    ]
    if colors is not None:
        col = np.asarray(colors).reshape(len(v), -1)[:, :3]
        lin = np.concatenate([_srgb_to_linear(col), np.ones((len(v), 1))], axis=1)
        blobs.append((lin * 65535 + 0.5).astype("<u2").tobytes())
        attrs["COLOR_0"] = len(accessors)
        accessors.append({"bufferView": len(accessors), "componentType": 5123, "normalized": True,
                          "count": len(v), "type": "VEC4"})
    blobs.append(idx.tobytes())
    accessors.append({"bufferView": len(accessors), "componentType": idx_type, "count": int(f.size), "type": "SCALAR"})
    views, binary, off = [], b"", 0
    for k, b in enumerate(blobs):
        views.append({"buffer": 0, "byteOffset": off, "byteLength": len(b),
                      "target": 34963 if k == len(blobs) - 1 else 34962})
        pad = b + b"\0" * (-len(b) % 4)
        binary += pad
        off += len(pad)
    gltf = {"asset": {"version": "2.0", "generator": "fastneus"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0, "name": "reconstruction"}],
            "meshes": [{"primitives": [{"attributes": attrs, "indices": len(accessors) - 1, "material": 0, "mode": 4}]}],
            "materials": [{"name": "matte", "doubleSided": True,
                           "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                                    "roughnessFactor": 0.85}}],
            "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(binary)}]}
    js = json.dumps(gltf, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(binary), 0x004E4942) + binary)


def view_rotation(c2w: np.ndarray) -> np.ndarray:
    """[3, 3] world -> viewer rotation that puts the viewer's default camera (on +z, y up) where an
    OpenCV camera with pose ``c2w`` is (x right, y down, looking along +z)."""
    r = np.asarray(c2w, dtype=np.float64)[:3, :3]
    return np.diag([1.0, -1.0, -1.0]) @ r.T


def viewer_html(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
                colors: np.ndarray | None = None, rotation: np.ndarray | None = None, max_faces: int = MAX_FACES,
                height_px: int = 520) -> tuple[str, dict]:
    """HTML of the 3D view (the viewer module inlined, the GLB as a data URI) and facts about it.

    Returns:
        (html, {"faces", "vertices", "faces_full", "glb_bytes", "decimated"}).
    """
    full = int(len(faces))
    v, f, n, c = decimate(vertices, faces, normals, colors, max_faces)
    glb = glb_bytes(v, f, n, c, rotation)
    uri = "data:model/gltf-binary;base64," + base64.b64encode(glb).decode("ascii")
    js = viewer_script()
    low = js.lower()
    if "</script" in low or "<script" in low:  # cannot be inlined safely: load it from a data URI instead
        script = f'<script type="module" src="data:text/javascript;base64,{base64.b64encode(js.encode()).decode()}"></script>'
    else:
        script = f'<script type="module" id="model-viewer-module">{js}</script>'
    facts = {"faces": int(len(f)), "vertices": int(len(v)), "faces_full": full, "glb_bytes": len(glb),
             "decimated": len(f) < full}
    alt = f"the reconstructed mesh, {len(f)} faces"
    tag = (f'<model-viewer id="mesh-view" src="{uri}" alt="{html.escape(alt)}" camera-controls '
           'camera-orbit="0deg 90deg auto" interaction-prompt="none" environment-image="neutral" '
           'shadow-intensity="0" exposure="1.1" tone-mapping="neutral" '
           f'style="width:100%;height:{int(height_px)}px;background:#eef0f3;border:1px solid #ccd"></model-viewer>')
    return script + "\n" + tag, facts
