"""The fastneus scene: a folder holding ``scene.json`` (format ``"fastneus-scene"``, version 1)
and the files it names (paths relative to the folder).

:meth:`Scene.load` validates everything and raises :class:`~fastneus.errors.FastneusError`
naming the file and field of the first problem; nothing is guessed. The elements of a scene
live in :mod:`fastneus.data.model`, the field checks in :mod:`fastneus.data.validate`, image
reading in :mod:`fastneus.data.images`, ground truth in :mod:`fastneus.data.groundtruth`;
the format is specified in docs/FORMAT.md.
"""
from __future__ import annotations

import copy
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fastneus.data.groundtruth import GT_KEYS, read_clean, read_depth, read_normal
from fastneus.data.images import check_image, image_info, image_size, read_mask, read_rgb, undistort
from fastneus.data.model import (Bounds, Camera, Frame, FrameProjector, Illumination, Pattern, Projector,
                                 parse_port, port_to_dict, to_list)
from fastneus.data.validate import (MAX_SIDE, as_dict, as_int, as_matrix, as_num, as_str, check_bounds_scale,
                                    check_faces_bounds, check_id, check_intrinsics, check_pose,
                                    check_principal_point, field_error, id_field, load_json, require)
from fastneus.errors import FastneusError
from fastneus.geometry.cameras import rigid_inverse
from fastneus.data.kinds import DEFAULT, get_projector_kind

FORMAT = "fastneus-scene"
VERSION = 1


@dataclass
class Scene:
    """A validated scene. File paths in ``frames``/``patterns`` are relative to ``root``."""

    root: Path
    cameras: dict[str, Camera]
    projectors: dict[str, Projector]
    patterns: dict[str, Pattern]
    frames: list[Frame]
    bounds: Bounds
    illumination: Illumination = field(default_factory=Illumination)
    gt_mesh: str | None = None
    units: str = "m"
    name: str = ""
    meta: dict = field(default_factory=dict)  # free-form provenance (e.g. how synth made it), kept on save
    response: str | None = None  # the photos' camera response (linear | srgb | gamma=G); None = not stated
    sensor_bits: int | None = None  # bits of the sensor values in 16-bit photos (right-aligned); None = decided
    _bits: int | None = field(default=None, repr=False, compare=False)  # the photos' bits per channel (photo_bits)
    _full: tuple | None = field(default=None, repr=False, compare=False)  # (full scale, why) of 16-bit photos
    _grey: bool | None = field(default=None, repr=False, compare=False)  # the photos are grey (grey)

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | os.PathLike) -> "Scene":
        """Load and validate a scene folder or its ``scene.json``.

        Raises:
            FastneusError: naming the file and field of the first problem.
        """
        path = Path(path)
        file = path / "scene.json" if path.is_dir() else path
        if not file.is_file():
            raise field_error("scene.json not found", file)
        data = load_json(file)
        return cls.from_dict(data, file.parent.resolve(), file=file)

    @classmethod
    def from_dict(cls, data: Any, root: str | os.PathLike, file=None, check_files: bool = True) -> "Scene":
        """Build a scene from the parsed ``scene.json`` content, validating everything.

        Args:
            data: the JSON object.
            root: folder the relative paths are resolved against.
            file: the file named in error messages (default ``root/scene.json``).
            check_files: also check that images/masks/patterns exist and have the right sizes.
        """
        root = Path(root)
        file = file if file is not None else root / "scene.json"
        d = as_dict(data, file, None)
        fmt = d.get("format")
        if fmt != FORMAT:
            raise field_error(f"unknown format {fmt!r}; expected {FORMAT!r}", file, "format")
        ver = d.get("version")
        if ver != VERSION:
            raise field_error(f"unsupported version {ver!r}; this fastneus reads version {VERSION}", file, "version")
        units = as_str(d.get("units", "m"), file, "units")
        name = d.get("name", "") or ""
        if not isinstance(name, str):
            raise field_error("expected a string", file, "name")

        b = as_dict(require(d, "bounds", file, ""), file, "bounds")
        bounds = Bounds(center=as_matrix(require(b, "center", file, "bounds"), (3,), file, "bounds.center"),
                        radius=as_num(require(b, "radius", file, "bounds"), file, "bounds.radius"))
        if bounds.radius <= 0:
            raise field_error("must be > 0", file, "bounds.radius")

        cameras: dict[str, Camera] = {}
        for cid, c in as_dict(require(d, "cameras", file, ""), file, "cameras").items():
            p = f"cameras.{check_id(cid, file, 'cameras')}"
            c = as_dict(c, file, p)
            dist = c.get("dist")
            cameras[cid] = Camera(
                id=cid, K=check_intrinsics(require(c, "K", file, p), file, f"{p}.K"),
                width=as_int(require(c, "width", file, p), file, f"{p}.width", maximum=MAX_SIDE),
                height=as_int(require(c, "height", file, p), file, f"{p}.height", maximum=MAX_SIDE),
                dist=np.zeros(5) if dist is None else as_matrix(dist, (5,), file, f"{p}.dist"),
                port=parse_port(c.get("port"), file, f"{p}.port"))
        if not cameras:
            raise field_error("no cameras", file, "cameras")
        for cid, cam in cameras.items():
            check_principal_point(cam.K, cam.width, cam.height, file, f"cameras.{cid}.K")

        projectors: dict[str, Projector] = {}
        for pid, pr in as_dict(d.get("projectors", {}), file, "projectors").items():
            p = f"projectors.{check_id(pid, file, 'projectors')}"
            pr = as_dict(pr, file, p)
            kind = get_projector_kind(pr.get("kind", DEFAULT), file, f"{p}.kind")  # its hooks: data/kinds.py
            fields = {"K": np.eye(3), "width": 1, "height": 1, **kind.call("parse", pr, file, p)}
            p2c = pr.get("proj_to_cam")
            projectors[pid] = Projector(id=pid, proj_to_cam=None if p2c is None else
                                        check_pose(p2c, file, f"{p}.proj_to_cam"), kind=kind.name, **fields)

        for pid, pj in projectors.items():
            if get_projector_kind(pj.kind).images:
                check_principal_point(pj.K, pj.width, pj.height, file, f"projectors.{pid}.K")
        patterns: dict[str, Pattern] = {}
        pattern_sizes: dict[str, tuple[int, int]] = {}
        for qid, q in as_dict(d.get("patterns", {}), file, "patterns").items():
            p = f"patterns.{check_id(qid, file, 'patterns')}"
            q = as_dict(q, file, p)
            patterns[qid] = Pattern(id=qid, file=as_str(require(q, "file", file, p), file, f"{p}.file"))
            if check_files:
                check_image(root, patterns[qid].file, None, file, f"{p}.file", kind="pattern")
                pattern_sizes[qid] = image_size(root / patterns[qid].file)

        fl = require(d, "frames", file, "")
        if not isinstance(fl, list):
            raise field_error("expected a list", file, "frames")
        if not fl:
            raise field_error("no frames: a scene needs at least one image", file, "frames")
        frames: list[Frame] = []
        frames_bits = frames_ch = None  # the first photo's bits per channel and channels (all must match)
        image_of: dict = {}  # path, resolved path, (device, inode) -> first frame using that photo
        for i, f in enumerate(fl):
            p = f"frames[{i}]"
            f = as_dict(f, file, p)
            cam = as_str(require(f, "camera", file, p), file, f"{p}.camera")
            if cam not in cameras:
                raise field_error(f"unknown camera id {cam!r}; known: {sorted(cameras)}", file, f"{p}.camera")
            image = as_str(require(f, "image", file, p), file, f"{p}.image")
            # the same photo by path, through a symbolic link or a hard link: one photo is one frame
            keys: set = {os.path.normpath(root / image), os.path.realpath(root / image)}
            try:
                st = os.stat(root / image)
                keys.add((st.st_dev, st.st_ino))
            except OSError:  # missing: reported with the file checks
                pass
            hit = next((image_of[k] for k in keys if k in image_of), None)
            if hit is not None:
                raise field_error(f"duplicate frame: image {image!r} is the same file as frames[{hit}].image "
                                  f"{fl[hit]['image']!r} (each photo is one frame)", file, f"{p}.image")
            image_of.update(dict.fromkeys(keys, i))
            c2w = check_pose(require(f, "cam_to_world", file, p), file, f"{p}.cam_to_world")
            view = as_int(f.get("view", i), file, f"{p}.view", minimum=0)
            mask = f.get("mask")
            if mask is not None:
                mask = as_str(mask, file, f"{p}.mask")
            fps: dict[str, FrameProjector] = {}
            for pid, fp in as_dict(f.get("projectors", {}), file, f"{p}.projectors").items():
                pp = id_field(f"{p}.projectors", pid)  # an unprintable id is quoted: the error stays one line
                if pid not in projectors:
                    raise field_error(f"unknown projector id {pid!r}; known: {sorted(projectors)}", file, pp)
                fp = as_dict(fp, file, pp)
                pat = fp.get("pattern")
                on = fp.get("on", True)
                if not isinstance(on, bool):
                    raise field_error("expected true or false", file, f"{pp}.on")
                if pat is not None and not get_projector_kind(projectors[pid].kind).images:
                    raise field_error(f"projector {pid!r} is a {projectors[pid].kind} projector; it shows no pattern, "
                                      "use on: true/false", file, f"{pp}.pattern")
                if pat is not None:
                    if not isinstance(pat, str) or pat not in patterns:
                        raise field_error(f"unknown pattern id {pat!r}; known: {sorted(patterns)}", file,
                                          f"{pp}.pattern")
                    pj = projectors[pid]
                    if check_files and pattern_sizes[pat] != (pj.width, pj.height):
                        w, h = pattern_sizes[pat]
                        raise field_error(f"pattern {pat!r} is {w}x{h} but projector {pid!r} is "
                                          f"{pj.width}x{pj.height}", file, f"{pp}.pattern")
                p2w = fp.get("proj_to_world")
                if projectors[pid].proj_to_cam is None:
                    if p2w is None:
                        raise field_error(f"projector {pid!r} is free (proj_to_cam null), so each frame needs "
                                          "proj_to_world", file, f"{pp}.proj_to_world")
                    p2w = check_pose(p2w, file, f"{pp}.proj_to_world")
                elif p2w is not None:
                    raise field_error(f"projector {pid!r} is rigged to the camera (proj_to_cam); "
                                      "a per-frame proj_to_world would contradict it", file, f"{pp}.proj_to_world")
                fps[pid] = FrameProjector(pattern=pat, proj_to_world=p2w, on=on)
            gt = {}
            for k, v in as_dict(f.get("gt", {}), file, f"{p}.gt").items():
                if k not in GT_KEYS:
                    raise field_error(f"unknown ground-truth key {k!r}; known: {list(GT_KEYS)}", file,
                                      id_field(f"{p}.gt", k))
                gt[k] = as_str(v, file, f"{p}.gt.{k}")
                if check_files and not (root / gt[k]).is_file():
                    raise field_error(f"file not found: {root / gt[k]}", file, f"{p}.gt.{k}")
            if check_files:
                size = (cameras[cam].width, cameras[cam].height)
                bits, ch = check_image(root, image, size, file, f"{p}.image")
                if frames_bits is None:
                    frames_bits, frames_ch = bits, ch
                elif bits != frames_bits:
                    raise field_error(f"image {image} is {bits}-bit but frames[0].image is {frames_bits}-bit; "
                                      "the photos of a scene share one bit depth", file, f"{p}.image")
                elif ch != frames_ch:
                    raise field_error(f"image {image} is {_colours(ch)} but frames[0].image is {_colours(frames_ch)}; "
                                      "the photos of a scene come from one kind of camera", file, f"{p}.image")
                if mask is not None:
                    check_image(root, mask, size, file, f"{p}.mask", kind="mask")
            frames.append(Frame(image=image, camera=cam, cam_to_world=c2w, projectors=fps, mask=mask,
                                view=view, gt=gt))
            check_faces_bounds(c2w, bounds.center, bounds.radius, "camera", file, f"{p}.cam_to_world")
            for pid, fp in fps.items():
                if fp.pattern is None:
                    continue
                p2c = projectors[pid].proj_to_cam
                check_faces_bounds(c2w @ p2c if p2c is not None else fp.proj_to_world, bounds.center, bounds.radius,
                                   "projector", file, f"projectors.{pid}.proj_to_cam" if p2c is not None
                                   else f"{p}.projectors.{pid}.proj_to_world")
        check_bounds_scale(bounds.center, bounds.radius,
                           [(f.cam_to_world, cameras[f.camera].K, cameras[f.camera].width) for f in frames], file)

        il = as_dict(d.get("illumination", {}), file, "illumination")
        known = il.get("known", False)
        if not isinstance(known, bool):
            raise field_error("expected true or false", file, "illumination.known")
        illum = Illumination(**{k: as_num(il[k], file, f"illumination.{k}") for k in ("i_r", "i_b", "ambient")
                                if k in il}, known=known)
        for k in ("i_r", "i_b", "ambient"):  # amounts of light: training starts log(i_r), log(i_b) from them
            if getattr(illum, k) < 0:
                raise field_error(f"is an amount of light and must be >= 0, got {getattr(illum, k)!r}", file,
                                  f"illumination.{k}")
        gt_mesh = as_dict(d.get("gt", {}) or {}, file, "gt").get("mesh")
        if gt_mesh is not None:
            gt_mesh = as_str(gt_mesh, file, "gt.mesh")
            if check_files and not (root / gt_mesh).is_file():
                raise field_error(f"file not found: {root / gt_mesh}", file, "gt.mesh")
        meta = as_dict(d.get("meta", {}) or {}, file, "meta")
        response = d.get("response")
        if response is not None:  # canonical spelling kept; training decodes the photos with it
            from fastneus.data.response import parse_response

            response = str(parse_response(response, file=file, field="response"))
        sensor_bits = d.get("sensor_bits")
        if sensor_bits is not None:
            if isinstance(sensor_bits, bool) or not isinstance(sensor_bits, int) or not 8 <= sensor_bits <= 16:
                raise field_error(f"expected a whole number of bits in 8..16, got {sensor_bits!r}", file, "sensor_bits")
            if frames_bits is not None and frames_bits <= 8:
                raise field_error("is for 16-bit photos (the bits their values use); these are 8-bit", file,
                                  "sensor_bits")
        return cls(root=root, cameras=cameras, projectors=projectors, patterns=patterns, frames=frames,
                   bounds=bounds, illumination=illum, gt_mesh=gt_mesh, units=units, name=name, meta=meta,
                   response=response, sensor_bits=sensor_bits, _bits=frames_bits, _grey=None if frames_ch is None else frames_ch == 1)

    # ------------------------------------------------------------------ saving
    def to_dict(self, rel_to: str | os.PathLike | None = None) -> dict:
        """The ``scene.json`` content; paths rewritten relative to ``rel_to`` when given."""
        root = Path(self.root).resolve()
        dest = Path(rel_to).resolve() if rel_to is not None else root

        def rp(p: str | None) -> str | None:
            if p is None or dest == root:
                return p
            return Path(os.path.relpath(root / p, dest)).as_posix()

        frames = []
        for f in self.frames:
            fd: dict[str, Any] = {"image": rp(f.image), "camera": f.camera, "cam_to_world": to_list(f.cam_to_world),
                                  "view": int(f.view), "projectors": {}}
            for pid, fp in f.projectors.items():
                e: dict[str, Any] = {"pattern": fp.pattern} if get_projector_kind(self.projectors[pid].kind).images \
                    else {"on": bool(fp.on)}
                if fp.proj_to_world is not None:
                    e["proj_to_world"] = to_list(fp.proj_to_world)
                fd["projectors"][pid] = e
            if f.mask is not None:
                fd["mask"] = rp(f.mask)
            if f.gt:
                fd["gt"] = {k: rp(v) for k, v in f.gt.items()}
            frames.append(fd)
        il = self.illumination
        return {
            "format": FORMAT, "version": VERSION, "units": self.units, "name": self.name,
            "bounds": {"center": to_list(self.bounds.center), "radius": float(self.bounds.radius)},
            "cameras": {c.id: {"K": to_list(c.K), "width": c.width, "height": c.height, "dist": to_list(c.dist),
                               **({"port": port_to_dict(c.port)} if c.port is not None else {})}
                        for c in self.cameras.values()},
            "projectors": {p.id: {**({"kind": p.kind} if p.kind != DEFAULT else {}),
                                  "proj_to_cam": to_list(p.proj_to_cam),
                                  **get_projector_kind(p.kind).call("serialise", p)} for p in self.projectors.values()},
            "patterns": {q.id: {"file": rp(q.file)} for q in self.patterns.values()},
            "frames": frames,
            "illumination": {"i_r": float(il.i_r), "i_b": float(il.i_b), "ambient": float(il.ambient),
                             "known": bool(il.known)},
            "gt": {"mesh": rp(self.gt_mesh)},
            **({"response": self.response} if self.response is not None else {}),
            **({"sensor_bits": int(self.sensor_bits)} if self.sensor_bits is not None else {}),
            "meta": copy.deepcopy(self.meta),
        }

    def save(self, folder: str | os.PathLike | None = None) -> Path:
        """Write ``scene.json`` into ``folder`` (default: the scene's root) atomically.

        Paths are rewritten relative to ``folder`` when it differs from the root, so the
        saved scene refers to the same files. Returns the path written.
        """
        folder = Path(folder if folder is not None else self.root)
        folder.mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.to_dict(rel_to=folder), indent=1)
        out = folder / "scene.json"
        fd, tmp = tempfile.mkstemp(prefix=".scene.", suffix=".json.tmp", dir=folder)
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(text + "\n")
            os.replace(tmp, out)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return out

    # ------------------------------------------------------------------ accessors
    def path(self, rel: str) -> Path:
        """Absolute path of a file named in the scene."""
        return Path(self.root) / rel

    def __len__(self) -> int:
        return len(self.frames)

    def frame_camera(self, i: int) -> Camera:
        return self.cameras[self.frames[i].camera]

    def cam_to_world(self, i: int) -> np.ndarray:
        """[4, 4] float64 camera->world pose of frame ``i``."""
        return self.frames[i].cam_to_world.copy()

    def world_to_cam(self, i: int) -> np.ndarray:
        return rigid_inverse(self.frames[i].cam_to_world)

    def proj_to_world(self, i: int, proj_id: str) -> np.ndarray:
        """[4, 4] projector->world of ``proj_id`` in frame ``i`` (rig or free pose)."""
        pj = self.projectors[proj_id]
        if pj.proj_to_cam is not None:
            return self.frames[i].cam_to_world @ pj.proj_to_cam
        fp = self.frames[i].projectors.get(proj_id)
        if fp is None or fp.proj_to_world is None:
            raise FastneusError(f"free projector {proj_id!r} has no pose in frame {i}",
                                field=f"frames[{i}].projectors.{proj_id}.proj_to_world")
        return fp.proj_to_world.copy()

    def world_to_proj(self, i: int, proj_id: str) -> np.ndarray:
        """[4, 4] world->projector of ``proj_id`` in frame ``i``."""
        return rigid_inverse(self.proj_to_world(i, proj_id))

    def active_projectors(self, i: int) -> list[tuple[str, str]]:
        """(projector id, pattern id) of every projector showing a pattern in frame ``i``."""
        return [(pid, fp.pattern) for pid, fp in self.frames[i].projectors.items() if fp.pattern is not None]

    def active_lasers(self, i: int) -> list[str]:
        """Ids of the laser-plane projectors lit in frame ``i``."""
        return [pid for pid, fp in self.frames[i].projectors.items()
                if self.projectors[pid].kind == "laser" and fp.on]

    def normalisation(self) -> np.ndarray:
        """[4, 4] float64 S mapping normalised -> world coordinates."""
        S = np.eye(4)
        S[:3, :3] *= self.bounds.radius
        S[:3, 3] = self.bounds.center
        return S

    def views(self) -> dict[int, list[int]]:
        """View id -> frame indices sharing that viewpoint (in frame order)."""
        out: dict[int, list[int]] = {}
        for i, f in enumerate(self.frames):
            out.setdefault(f.view, []).append(i)
        return out

    def _first_photo(self) -> None:
        """``_bits`` and ``_grey`` from the first photo's header (a scene built without the load's checks)."""
        info = image_info(self.path(self.frames[0].image)) if self.frames else None
        self._bits = 8 if info is None else int(info[3])
        self._grey = info is not None and int(info[2]) == 1

    @property
    def photo_bits(self) -> int:
        """Bits per channel of the photos (8 or 16; all alike, checked on load)."""
        if self._bits is None:
            self._first_photo()
        return self._bits

    def photo_full_scale(self) -> tuple[int, str]:
        """(the value that is full scale in the 16-bit photos, why): ``2**sensor_bits - 1`` when
        scene.json states ``sensor_bits``, else decided from the brightest value of all photos (each
        read once more): a 10-, 12- or 14-bit camera writes its values right-aligned in a 16-bit
        file (as OpenCV and most SDKs save Mono12), and read as 16-bit light they would be 4-64x too
        dark (on a 12-bit copy of a dark-room capture the background prior saw 99 % of the pixels as
        empty and carved the object away). The smallest of 10 / 12 / 14 / 16 bits that holds that
        value is taken: a dim 12-bit capture taken for 10 bits is only brighter, an exposure."""
        if self._full is None:
            if self.sensor_bits is not None:
                b = int(self.sensor_bits)
                self._full = (2 ** b - 1, f"{b}-bit values, scene.json's sensor_bits")
            else:
                mx = 0
                for i, f in enumerate(self.frames):
                    im = read_rgb(self.path(f.image), self.root / "scene.json", f"frames[{i}].image", deep=True)
                    mx = max(mx, int(im.max()))
                b = next(b for b in (10, 12, 14, 16) if mx <= 2 ** b - 1)
                why = "16-bit values" if b == 16 else \
                    (f"{b}-bit values: the brightest photo value is {mx}, a {b}-bit camera's right-aligned values, "
                     "scaled to full range (state sensor_bits in scene.json if they are not)")
                self._full = (2 ** b - 1, why)
        return self._full

    @property
    def grey(self) -> bool:
        """Whether the photos are grey (one channel: a monochrome camera; all alike, checked on load).

        They are read as three equal channels, and the projectors' light as the grey a monochrome
        sensor sees (:meth:`pattern_image`, :func:`fastneus.light.greyed`): the model then renders
        three equal channels too, and i_r takes the sensor's sensitivity to the projectors' colour.
        """
        if self._grey is None:
            self._first_photo()
        return self._grey

    def image(self, i: int) -> np.ndarray:
        """uint8 [H, W, 3] RGB image of frame ``i`` (undistorted if the camera has distortion).

        16-bit photos come as 8-bit sRGB codes of their linear light
        (:func:`fastneus.data.response.deep_to_u8`: decoded with :func:`deep_file_response`); training
        then decodes them as sRGB (``resolve_response``)."""
        f = self.frames[i]
        deep = self.photo_bits > 8
        im = read_rgb(self.path(f.image), self.root / "scene.json", f"frames[{i}].image", deep=deep)
        if deep and im.dtype == np.uint16:
            from fastneus.data.response import deep_file_response, deep_to_u8

            full, why = self.photo_full_scale()
            if int(im.max()) > full:
                raise FastneusError(f"has values up to {int(im.max())}, above the full scale {full} of the photos "
                                    f"({why}); state the camera's bits in scene.json's sensor_bits",
                                    file=self.path(f.image), field=f"frames[{i}].image")
            im = deep_to_u8(im, deep_file_response(self)[0], full)
        cam = self.frame_camera(i)
        return undistort(im, cam.K, cam.dist)

    def mask(self, i: int) -> np.ndarray | None:
        """float32 [H, W] in [0, 1] (soft edges kept) or None when the frame has no mask."""
        f = self.frames[i]
        if f.mask is None:
            return None
        m = read_mask(self.path(f.mask), self.root / "scene.json", f"frames[{i}].mask")
        cam = self.frame_camera(i)
        return undistort(m, cam.K, cam.dist)

    def pattern_image(self, pid: str) -> np.ndarray:
        """uint8 [h, w, 3] RGB pattern ``pid``; with grey photos its grey (:func:`fastneus.light.grey_rgb`)."""
        im = read_rgb(self.path(self.patterns[pid].file), self.root / "scene.json", f"patterns.{pid}.file")
        if self.grey:
            from fastneus.light import grey_rgb

            im = grey_rgb(im)
        return im

    def gt_depth(self, i: int) -> np.ndarray | None:
        """float32 [H, W] ground-truth z-depth (world units, 0 = background) or None."""
        rel = self.frames[i].gt.get("depth")
        if rel is None:
            return None
        return read_depth(self.path(rel), self.root / "scene.json", f"frames[{i}].gt.depth")

    def gt_normal(self, i: int) -> np.ndarray | None:
        """float32 [H, W, 3] ground-truth world normals (zero = background) or None."""
        rel = self.frames[i].gt.get("normal")
        if rel is None:
            return None
        return read_normal(self.path(rel), self.root / "scene.json", f"frames[{i}].gt.normal")

    def gt_clean(self, i: int) -> np.ndarray | None:
        """uint8 [H, W, 3] RGB pattern-free image or None."""
        rel = self.frames[i].gt.get("clean")
        if rel is None:
            return None
        return read_clean(self.path(rel), self.root / "scene.json", f"frames[{i}].gt.clean")

    def subset(self, frame_indices) -> "Scene":
        """A scene with only the given frames (same root, cameras, projectors, patterns)."""
        idx = [int(i) for i in frame_indices]
        if not idx:
            raise FastneusError("a subset needs at least one frame", field="frames")
        for i in idx:
            if not 0 <= i < len(self.frames):
                raise FastneusError(f"frame index {i} out of range 0..{len(self.frames) - 1}", field="frames")
        s = copy.copy(self)
        s.frames = [copy.deepcopy(self.frames[i]) for i in idx]
        return s


def _colours(channels: int) -> str:
    """'grey' or 'colour' for a photo's channel count (error messages)."""
    return "grey" if channels == 1 else "colour"


def view_frames(scene, frames: list[int]) -> dict[int, list[int]]:
    """Training frames grouped by viewpoint (view id -> frame indices, in order)."""
    out: dict[int, list[int]] = {}
    for i in frames:
        out.setdefault(scene.frames[i].view, []).append(i)
    return out
