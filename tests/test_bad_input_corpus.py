"""A corpus of bad input across every verb and format.

Every case builds one broken input from a small valid base (scene.json, ActiveNeuS npz,
NeuS npz, OpenCV calibration, COLMAP text, images, masks, patterns, configs, CLI
arguments, run folders, checkpoints) and runs the CLI in-process. Each must exit non-zero
with exactly one line that names the file and/or field at fault, never a traceback or an
'internal error', and must leave the output folder, which holds an earlier good result,
byte for byte as it was.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
import torch

from conftest import SMALL_RUN
from fastneus.cli import main

CASES: dict[str, Callable] = {}


def case(name: str):
    def reg(fn):
        assert name not in CASES
        CASES[name] = fn
        return fn
    return reg


# --------------------------------------------------------------------------- bases
@pytest.fixture(scope="module")
def bases(small_scene, tmp_path_factory):
    """Valid inputs of every kind, built once; cases copy what they break."""
    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.formats.activeneus import write_activeneus
    from fastneus.train.trainer import Trainer

    root = tmp_path_factory.mktemp("corpus")
    scene = Scene.load(small_scene)
    an = root / "an"
    write_activeneus(scene, an)

    # NeuS/DTU: world_mat = K [R | t] (integer pixel centres), scale_mat, image/ and mask/
    neus = root / "neus"
    shutil.copytree(an / "image", neus / "image")
    shutil.copytree(an / "mask", neus / "mask")
    K = scene.frame_camera(0).K.copy()
    K[:2, 2] -= 0.5
    arrays = {}
    for i in range(len(scene.frames)):
        P = np.eye(4)
        P[:3, :3] = K
        arrays[f"world_mat_{i}"] = P @ scene.world_to_cam(i)
        arrays[f"scale_mat_{i}"] = scene.normalisation()
    np.savez(neus / "cameras_sphere.npz", **arrays)

    # OpenCV procam calibration (Moreno-Taubin keys) matching projector proj0, in metres
    pj = scene.projectors["proj0"]
    Kp = pj.K.copy()
    Kp[:2, 2] -= 0.5
    cam_to_proj = np.linalg.inv(pj.proj_to_cam)
    calib = {"cam_K": K, "cam_kc": np.zeros((1, 5)), "proj_K": Kp, "proj_kc": np.zeros((1, 5)),
             "R": cam_to_proj[:3, :3], "T": cam_to_proj[:3, 3].reshape(3, 1)}
    fs = cv2.FileStorage(str(root / "calib.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in calib.items():
        fs.write(k, np.ascontiguousarray(v, dtype=np.float64))
    fs.release()
    pattern = small_scene / scene.patterns[scene.frames[0].projectors["proj0"].pattern].file

    # COLMAP text model of the same poses
    from scipy.spatial.transform import Rotation

    cm = root / "colmap"
    cm.mkdir()
    (cm / "cameras.txt").write_text(f"1 PINHOLE 24 24 {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    lines = []
    for i in range(len(scene.frames)):
        w2c = scene.world_to_cam(i)
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        lines += [f"{i + 1} {w} {x} {y} {z} {' '.join(map(str, w2c[:3, 3]))} 1 {i:03d}.png", ""]
    (cm / "images.txt").write_text("\n".join(lines) + "\n")

    # a run folder: checkpoint (no training needed) and run.json
    run = root / "run"
    Trainer(scene, load_config("cpu-quick", SMALL_RUN), run, "cpu").save()
    (run / "run.json").write_text(json.dumps({"scene": str(small_scene)}))
    return {"fn": small_scene, "an": an, "neus": neus, "calib": root / "calib.yml", "images": small_scene / "images",
            "pattern": pattern, "poses": small_scene / "scene.json", "colmap": cm, "run": run}


class Ctx:
    """One case's workspace: copies of the bases, output folders holding an earlier good result."""

    def __init__(self, bases: dict, tmp: Path):
        self.b, self.tmp = bases, tmp

    def copy(self, kind: str) -> Path:
        dst = self.tmp / kind
        if not dst.exists():
            shutil.copytree(self.b[kind], dst)
        return dst

    # --- fastneus scene.json
    def json(self, edit: Callable[[dict], None]) -> Path:
        d = self.copy("fn")
        data = json.loads((d / "scene.json").read_text())
        edit(data)
        (d / "scene.json").write_text(json.dumps(data))
        return d

    def fn_file(self, rel: str) -> Path:
        return self.copy("fn") / rel

    # --- npz scenes
    def npz(self, kind: str, drop: tuple[str, ...] = (), **entries) -> Path:
        d = self.copy(kind)
        with np.load(d / "cameras_sphere.npz", allow_pickle=True) as z:  # our own base file: trusted
            arrays = {k: z[k] for k in z.files if k not in drop}
        arrays.update(entries)
        np.savez(d / "cameras_sphere.npz", **arrays)
        return d

    def npz_value(self, kind: str, key: str) -> np.ndarray:
        with np.load(self.b[kind] / "cameras_sphere.npz", allow_pickle=True) as z:
            return np.array(z[key])

    # --- output folders with an earlier result
    def run_out(self) -> Path:
        """A finished run's folder (the earlier result a failing train must not touch); fastneus's mark
        says it is a run, so --overwrite may replace it once the inputs are valid."""
        out = self.tmp / "out_run"
        out.mkdir(exist_ok=True)
        for name, text in (("metrics.json", '{"chamfer": 1}'), ("mesh.ply", "earlier mesh"), ("checkpoint.pt", "x"),
                           (".fastneus-run.json", '{"written_by": "fastneus"}')):
            (out / name).write_text(text)
        return out

    def scene_out(self) -> Path:
        out = self.tmp / "out_scene"
        (out / "image").mkdir(parents=True, exist_ok=True)
        (out / "scene.json").write_text('{"earlier": "scene"}')
        (out / "image" / "000.png").write_bytes(b"earlier image")
        return out

    def run(self) -> Path:
        """A copy of the base run folder, plus earlier exports."""
        run = self.copy("run")
        (run / "mesh.ply").write_text("earlier mesh")
        (run / "metrics.json").write_text('{"chamfer": 1}')
        return run

    # --- argv builders: (argv, folder that must not change)
    def train(self, scene: Path, *extra: str, overwrite: bool = True):
        out = self.run_out()
        return (["train", str(scene), "--out", str(out), "--device", "cpu", *(["--overwrite"] if overwrite else []),
                 *SMALL_RUN, *extra], out)

    def import_calib(self, calib=None, images=None, pattern=None, poses=None, colmap=None, *extra: str):
        out = self.scene_out()
        where = ["--colmap", str(colmap)] if colmap else ["--poses", str(poses or self.b["poses"])]
        return (["import-calib", str(calib or self.b["calib"]), "--images", str(images or self.b["images"]),
                 "--patterns", str(pattern or self.b["pattern"]), *where, "--units", "m", "--out", str(out),
                 *extra], out)

    def on_run(self, verb: str, run: Path | None = None, *extra: str):
        run = run or self.run()
        return [verb, str(run), "--device", "cpu", *extra], run


def _png(path: Path, img: np.ndarray) -> None:
    assert cv2.imwrite(str(path), img)


def _first_pattern_rel(d: dict) -> tuple[str, str]:
    qid = d["frames"][0]["projectors"]["proj0"]["pattern"]
    return qid, d["patterns"][qid]["file"]


# --------------------------------------------------------------------------- scene.json (train)
@case("json-truncated")
def _(c):
    d = c.copy("fn")
    (d / "scene.json").write_text((d / "scene.json").read_text()[:200])
    return c.train(d) + (["scene.json", "invalid JSON"],)


@case("json-not-an-object")
def _(c):
    d = c.copy("fn")
    (d / "scene.json").write_text("[1, 2, 3]")
    return c.train(d) + (["scene.json", "expected an object"],)


@case("json-missing-frames")
def _(c):
    return c.train(c.json(lambda d: d.pop("frames"))) + (["scene.json", "frames"],)


@case("json-zero-frames")
def _(c):
    return c.train(c.json(lambda d: d.update(frames=[]))) + (["scene.json", "frames", "no frames"],)


@case("json-wrong-format")
def _(c):
    return c.train(c.json(lambda d: d.update(format="nerf"))) + (["scene.json", "format"],)


@case("json-K-nan")
def _(c):
    return c.train(c.json(lambda d: d["cameras"]["cam0"]["K"][0].__setitem__(0, float("nan")))) + \
        (["scene.json", "cameras.cam0.K", "non-finite"],)


@case("json-K-singular")
def _(c):
    return c.train(c.json(lambda d: d["cameras"]["cam0"]["K"][1].__setitem__(1, 0.0))) + \
        (["scene.json", "cameras.cam0.K", "fy > 0"],)


@case("json-K-wrong-shape")
def _(c):
    return c.train(c.json(lambda d: d["cameras"]["cam0"].update(K=[[1, 0], [0, 1]]))) + \
        (["scene.json", "cameras.cam0.K", "shape"],)


@case("json-width-string")
def _(c):
    return c.train(c.json(lambda d: d["cameras"]["cam0"].update(width="24"))) + \
        (["scene.json", "cameras.cam0.width"],)


@case("json-pose-not-rigid")
def _(c):
    def edit(d):
        d["frames"][0]["cam_to_world"] = (np.asarray(d["frames"][0]["cam_to_world"]) @ np.diag([2, 2, 2, 1])).tolist()
    return c.train(c.json(edit)) + (["scene.json", "frames[0].cam_to_world", "orthonormal"],)


@case("json-pose-inf")
def _(c):
    return c.train(c.json(lambda d: d["frames"][1]["cam_to_world"][0].__setitem__(3, float("inf")))) + \
        (["scene.json", "frames[1].cam_to_world", "non-finite"],)


@case("json-camera-facing-away")
def _(c):
    def edit(d):  # rotate the camera 180 degrees about its y axis: it looks away from the object
        d["frames"][2]["cam_to_world"] = (np.asarray(d["frames"][2]["cam_to_world"]) @ np.diag([-1, 1, -1, 1])).tolist()
    return c.train(c.json(edit)) + (["scene.json", "frames[2].cam_to_world", "behind this camera"],)


@case("json-projector-behind-scene")
def _(c):
    def edit(d):
        T = np.asarray(d["projectors"]["proj1"]["proj_to_cam"]) @ np.diag([-1, 1, -1, 1])
        d["projectors"]["proj1"]["proj_to_cam"] = T.tolist()
    return c.train(c.json(edit)) + (["scene.json", "projectors.proj1.proj_to_cam", "behind this projector"],)


@case("json-unknown-camera")
def _(c):
    return c.train(c.json(lambda d: d["frames"][0].update(camera="nikon"))) + (["scene.json", "frames[0].camera"],)


@case("json-bounds-radius-zero")
def _(c):
    return c.train(c.json(lambda d: d["bounds"].update(radius=0))) + (["scene.json", "bounds.radius"],)


@case("json-illumination-nan")
def _(c):
    return c.train(c.json(lambda d: d["illumination"].update(i_r=float("nan")))) + \
        (["scene.json", "illumination.i_r", "finite"],)


@case("json-duplicate-frame")
def _(c):
    return c.train(c.json(lambda d: d["frames"][1].update(image=d["frames"][0]["image"]))) + \
        (["scene.json", "frames[1].image", "duplicate"],)


@case("json-gt-depth-missing")
def _(c):
    return c.train(c.json(lambda d: d["frames"][0]["gt"].update(depth="depth/nope.npy"))) + \
        (["scene.json", "frames[0].gt.depth", "not found"],)


# --------------------------------------------------------------------------- images, masks, patterns (train)
@case("image-missing")
def _(c):
    c.fn_file("images/000.png").unlink()
    return c.train(c.copy("fn")) + (["scene.json", "frames[0].image", "not found"],)


@case("image-truncated")
def _(c):
    p = c.fn_file("images/001.png")
    p.write_bytes(p.read_bytes()[:120])
    return c.train(c.copy("fn")) + (["frames[1].image", "cannot read image"],)


@case("image-size-mismatch")
def _(c):
    _png(c.fn_file("images/002.png"), np.zeros((20, 24, 3), np.uint8))
    return c.train(c.copy("fn")) + (["scene.json", "frames[2].image", "24x20"],)


@case("image-grey-among-colour")
def _(c):
    _png(c.fn_file("images/001.png"), np.zeros((24, 24), np.uint8))  # grey photos are read; a mix is not
    return c.train(c.copy("fn")) + (["scene.json", "frames[1].image", "grey"],)


@case("image-rgba")
def _(c):
    _png(c.fn_file("images/000.png"), np.zeros((24, 24, 4), np.uint8))
    return c.train(c.copy("fn")) + (["scene.json", "frames[0].image", "alpha"],)


@case("image-16bit-among-8bit")
def _(c):
    _png(c.fn_file("images/001.png"), np.zeros((24, 24, 3), np.uint16))
    return c.train(c.copy("fn")) + (["scene.json", "frames[1].image", "16-bit"],)


@case("mask-size-mismatch")
def _(c):
    _png(c.fn_file("masks/000.png"), np.zeros((24, 12), np.uint8))
    return c.train(c.copy("fn")) + (["scene.json", "frames[0].mask", "12x24"],)


@case("mask-rgba")
def _(c):
    _png(c.fn_file("masks/001.png"), np.zeros((24, 24, 4), np.uint8))
    return c.train(c.copy("fn")) + (["scene.json", "frames[1].mask", "alpha"],)


@case("masks-all-empty")
def _(c):
    for i in range(3):
        _png(c.fn_file(f"masks/{i:03d}.png"), np.zeros((24, 24), np.uint8))
    return c.train(c.copy("fn")) + (["masks/000.png", "frames[0].mask", "empty"],)


@case("pattern-missing")
def _(c):
    d = json.loads(c.fn_file("scene.json").read_text())
    qid, rel = _first_pattern_rel(d)
    c.fn_file(rel).unlink()
    return c.train(c.copy("fn")) + (["scene.json", f"patterns.{qid}.file", "not found"],)


@case("pattern-size-mismatch")
def _(c):
    d = json.loads(c.fn_file("scene.json").read_text())
    _, rel = _first_pattern_rel(d)
    _png(c.fn_file(rel), np.zeros((10, 10, 3), np.uint8))
    return c.train(c.copy("fn")) + (["scene.json", "frames[0].projectors.proj0.pattern", "10x10"],)


@case("pattern-16bit")
def _(c):
    d = json.loads(c.fn_file("scene.json").read_text())
    qid, rel = _first_pattern_rel(d)
    _png(c.fn_file(rel), np.zeros((48, 64, 3), np.uint16))
    return c.train(c.copy("fn")) + (["scene.json", f"patterns.{qid}.file", "16-bit"],)


# --------------------------------------------------------------------------- ActiveNeuS npz (train)
@case("an-npz-truncated")
def _(c):
    d = c.copy("an")
    p = d / "cameras_sphere.npz"
    p.write_bytes(p.read_bytes()[:300])
    return c.train(d) + (["cameras_sphere.npz", "unreadable npz"],)


@case("an-npz-not-a-zip")
def _(c):
    d = c.copy("an")
    (d / "cameras_sphere.npz").write_text("cam_mat_0 = 1\n")
    return c.train(d) + (["cameras_sphere.npz", "not an npz archive"],)


@case("an-missing-key")
def _(c):
    return c.train(c.npz("an", drop=("cam_mat_1",))) + (["cameras_sphere.npz", "cam_mat_1", "missing"],)


@case("an-pose-wrong-shape")
def _(c):
    return c.train(c.npz("an", cam_pose_0=np.eye(4)[:3])) + (["cameras_sphere.npz", "cam_pose_0", "shape"],)


@case("an-K-nan")
def _(c):
    K = c.npz_value("an", "cam_mat_0")
    K[0, 2] = np.nan
    return c.train(c.npz("an", cam_mat_0=K)) + (["cameras_sphere.npz", "cam_mat_0", "non-finite"],)


@case("an-K-singular")
def _(c):
    K = c.npz_value("an", "cam_mat_0")
    K[0, 0] = 0.0
    return c.train(c.npz("an", cam_mat_0=K)) + (["cameras_sphere.npz", "cam_mat_0", "fx, fy > 0"],)


@case("an-proj-mat-wrong-shape")
def _(c):
    return c.train(c.npz("an", proj_mat_0=np.eye(4))) + (["cameras_sphere.npz", "proj_mat_0", "shape"],)


@case("an-projector-behind-scene")
def _(c):
    T = c.npz_value("an", "cam_proj_pose_1")
    T[2] = np.diag([-1, 1, -1, 1]) @ T[2]  # projector 2 turned round: z -> -z in its frame
    return c.train(c.npz("an", cam_proj_pose_1=T)) + (["cameras_sphere.npz", "cam_proj_pose_1[2]", "behind"],)


@case("an-scale-mat-differs")
def _(c):
    return c.train(c.npz("an", scale_mat_1=np.diag([3.0, 3, 3, 1]))) + (["cameras_sphere.npz", "scale_mat_1"],)


@case("an-illumination-payload")
def _(c):
    class Payload:
        def __reduce__(self):
            return exec, (f"open({str(c.tmp / 'pwned')!r}, 'w').close()",)
    return c.train(c.npz("an", illumination_params=np.array(Payload(), dtype=object))) + \
        (["cameras_sphere.npz", "illumination_params", "refused"],)


@case("an-illumination-strings")
def _(c):
    ip = np.array({"ambient": "1", "diffuse": "0.4", "emissive": "0.1"}, dtype=object)
    return c.train(c.npz("an", illumination_params=ip)) + (["cameras_sphere.npz", "illumination_params.ambient"],)


@case("an-pickled-matrix")
def _(c):
    return c.train(c.npz("an", cam_mat_0=np.array({"K": 1}, dtype=object))) + \
        (["cameras_sphere.npz", "cam_mat_0", "pickled"],)


@case("an-masks-count")
def _(c):
    d = c.copy("an")
    (d / "mask" / "002.png").unlink()
    return c.train(d) + (["mask", "2 masks for 3 images"],)


@case("an-zero-frames")
def _(c):
    d = c.copy("an")
    shutil.rmtree(d / "image")
    (d / "image").mkdir()
    return c.train(d) + (["image", "no images"],)


@case("an-pattern-name")
def _(c):
    d = c.copy("an")
    (d / "pattern" / "000_00.png").rename(d / "pattern" / "first.png")
    return c.train(d) + (["first.png", "NNN_KK"],)


# --------------------------------------------------------------------------- NeuS npz (train)
@case("neus-singular-world-mat")
def _(c):
    W = c.npz_value("neus", "world_mat_0")
    W[:3, :3] = 0
    return c.train(c.npz("neus", world_mat_0=W)) + (["cameras_sphere.npz", "world_mat_0", "singular"],)


@case("neus-nan")
def _(c):
    W = c.npz_value("neus", "world_mat_1")
    W[1, 1] = np.inf
    return c.train(c.npz("neus", world_mat_1=W)) + (["cameras_sphere.npz", "world_mat_1", "non-finite"],)


@case("neus-missing-world-mat")
def _(c):
    return c.train(c.npz("neus", drop=("world_mat_2",))) + (["cameras_sphere.npz", "world_mat_2", "missing"],)


@case("neus-wrong-shape")
def _(c):
    return c.train(c.npz("neus", world_mat_0=np.ones(5))) + (["cameras_sphere.npz", "world_mat_0", "shape"],)


# --------------------------------------------------------------------------- OpenCV calibration (import-calib)
def _calib(c, name: str = "c.yml", text: str | None = None, **changes) -> Path:
    """The base calibration with keys replaced (None drops a key), or ``text`` verbatim."""
    p = c.tmp / name
    if text is not None:
        p.write_text(text)
        return p
    src = cv2.FileStorage(str(c.b["calib"]), cv2.FILE_STORAGE_READ)
    keys = {k: src.getNode(k).mat() for k in src.root().keys()}
    src.release()
    keys.update(changes)
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    for k, v in keys.items():
        if v is not None:
            fs.write(k, np.asarray(v, dtype=np.float64))
    fs.release()
    return p


@case("calib-malformed-yaml")
def _(c):
    return c.import_calib(_calib(c, text="%YAML:1.0\ncam_K: !!opencv-matrix\n  rows: [3\n")) + (["c.yml"],)


@case("calib-malformed-xml")
def _(c):
    return c.import_calib(_calib(c, "c.xml", text="<?xml version=\"1.0\"?><opencv_storage><cam_K>")) + (["c.xml"],)


@case("calib-missing-key")
def _(c):
    return c.import_calib(_calib(c, proj_K=None)) + (["c.yml", "proj_K", "missing"],)


@case("calib-K-nan")
def _(c):
    K = np.eye(3)
    K[0, 0] = np.nan
    return c.import_calib(_calib(c, cam_K=K)) + (["c.yml", "cam_K", "non-finite"],)


@case("calib-K-singular")
def _(c):
    return c.import_calib(_calib(c, cam_K=np.diag([0.0, 30.0, 1.0]))) + (["c.yml", "cam_K"],)


@case("calib-R-not-rotation")
def _(c):
    return c.import_calib(_calib(c, R=np.diag([1.0, 1.0, 2.0]))) + (["c.yml", "R", "orthonormal"],)


@case("calib-unknown-layout")
def _(c):
    return c.import_calib(_calib(c, text="%YAML:1.0\n---\nfoo: 1\n")) + (["c.yml", "layout"],)


@case("calib-image-size-mismatch")
def _(c):
    imgs = c.tmp / "imgs"
    shutil.copytree(c.b["images"], imgs)
    _png(imgs / "001.png", np.zeros((30, 24, 3), np.uint8))
    return c.import_calib(images=imgs) + (["001.png", "--images", "24x30"],)


@case("calib-pattern-size-mismatch")
def _(c):
    pat = c.tmp / "pattern.png"
    _png(pat, np.zeros((40, 64, 3), np.uint8))
    return c.import_calib(_calib(c, proj_width=np.array([[64.0]]), proj_height=np.array([[48.0]])),
                          pattern=pat) + (["pattern.png", "--patterns", "64x40"],)


@case("calib-poses-count")
def _(c):
    d = json.loads(c.b["poses"].read_text())
    d["frames"] = d["frames"][:2]
    p = c.tmp / "poses.json"
    p.write_text(json.dumps(d))
    return c.import_calib(poses=p) + (["poses.json", "frames", "2 frames but 3 images"],)


# --------------------------------------------------------------------------- COLMAP text (import-calib --colmap)
def _colmap(c, images_txt: str | None = None, cameras_txt: str | None = None) -> Path:
    d = c.tmp / "colmap"
    shutil.copytree(c.b["colmap"], d)
    if images_txt is not None:
        (d / "images.txt").write_text(images_txt)
    if cameras_txt is not None:
        (d / "cameras.txt").write_text(cameras_txt)
    return d


@case("colmap-malformed-line")
def _(c):
    return c.import_calib(colmap=_colmap(c, images_txt="1 0.5 0.5 nope\n\n")) + (["images.txt", "cannot parse"],)


@case("colmap-duplicate-image")
def _(c):
    lines = (c.b["colmap"] / "images.txt").read_text().splitlines()
    dup = lines[:2] + ["9" + lines[0][1:], ""] + lines[2:]
    return c.import_calib(colmap=_colmap(c, images_txt="\n".join(dup) + "\n")) + \
        (["images.txt", "000.png", "duplicate"],)


@case("colmap-nan-pose")
def _(c):
    t = (c.b["colmap"] / "images.txt").read_text().split(" ")
    t[1] = "nan"
    return c.import_calib(colmap=_colmap(c, images_txt=" ".join(t))) + (["images.txt", "bad pose"],)


@case("colmap-image-not-in-model")
def _(c):
    lines = (c.b["colmap"] / "images.txt").read_text().splitlines()
    return c.import_calib(colmap=_colmap(c, images_txt="\n".join(lines[:4]) + "\n")) + \
        (["images.txt", "002.png", "not in the COLMAP model"],)


@case("colmap-binary-cameras")
def _(c):
    d = _colmap(c)
    (d / "cameras.txt").write_bytes(b"\xff\xfe\x00binary")
    return c.import_calib(colmap=d) + (["cameras.txt", "text"],)


# --------------------------------------------------------------------------- configs
@case("config-malformed-yaml")
def _(c):
    p = c.tmp / "my.yaml"
    p.write_text("steps: [1, 2\n")
    return c.train(c.b["fn"], "--config", str(p)) + (["my.yaml", "cannot read config"],)


@case("config-not-a-mapping")
def _(c):
    p = c.tmp / "my.yaml"
    p.write_text("- steps\n- 10\n")
    return c.train(c.b["fn"], "--config", str(p)) + (["my.yaml", "mapping"],)


@case("config-unknown-key")
def _(c):
    p = c.tmp / "my.yaml"
    p.write_text("stepz: 10\n")
    return c.train(c.b["fn"], "--config", str(p)) + (["my.yaml", "stepz"],)


@case("config-missing-file")
def _(c):
    return c.train(c.b["fn"], "--config", str(c.tmp / "none.yaml")) + (["none.yaml", "not found"],)


@case("config-nan-value")
def _(c):
    return c.train(c.b["fn"], "eikonal_weight=.nan") + (["command line", "eikonal_weight", "finite"],)


@case("config-wrong-type")
def _(c):
    return c.train(c.b["fn"], "frames=abc") + (["command line", "frames"],)


@case("config-frames-out-of-range")
def _(c):
    return c.train(c.b["fn"], "frames=[0,7]") + (["frames", "out of range"],)


# --------------------------------------------------------------------------- CLI arguments
@case("cli-out-is-a-file")
def _(c):
    f = c.tmp / "afile"
    f.write_text("earlier")
    argv, _ = c.train(c.b["fn"])
    argv[argv.index("--out") + 1] = str(f)
    return argv, f, ["afile", "--out", "not a folder"]


@case("cli-convert-out-is-a-file")
def _(c):
    f = c.tmp / "afile"
    f.write_text("earlier")
    return ["convert", str(c.b["an"]), "--to", "fastneus", "--out", str(f)], f, ["afile", "--out", "not a folder"]


@case("cli-patterns-out-is-a-file")
def _(c):
    f = c.tmp / "afile"
    f.write_text("earlier")
    return ["patterns", "--kind", "grid", "--size", "32x16", "--out", str(f)], f, ["afile", "--out"]


@case("cli-synth-out-is-a-file")
def _(c):
    f = c.tmp / "afile"
    f.write_text("earlier")
    return ["synth", "--shape", "sphere", "--views", "1", "--size", "8x8", "--device", "cpu", "--out", str(f)], f, \
        ["afile", "--out", "not a folder"]


@case("cli-demo-out-is-a-file")
def _(c):
    f = c.tmp / "afile"
    f.write_text("earlier")
    return ["demo", "--device", "cpu", "--out", str(f)], f, ["afile", "--out", "not a folder"]


@case("cli-synth-bad-int")
def _(c):
    out = c.scene_out()
    return ["synth", "--shape", "sphere", "--views", "two", "--out", str(out)], out, ["--views", "invalid int"]


@case("cli-synth-bad-size")
def _(c):
    out = c.scene_out()
    return ["synth", "--shape", "sphere", "--size", "0x10", "--out", str(out)], out, ["--size"]


@case("cli-convert-downscale-zero")
def _(c):
    out = c.scene_out()
    return ["convert", str(c.b["fn"]), "--to", "activeneus", "--downscale", "0", "--out", str(out)], out, \
        ["--downscale"]


@case("cli-resume-and-overwrite")
def _(c):
    return c.train(c.b["fn"], "--resume") + (["--resume", "--overwrite"],)


@case("cli-bad-device")
def _(c):
    return c.train(c.b["fn"], "--device", "tpu") + (["--device", "tpu"],)


@case("cli-render-frame-out-of-range")
def _(c):
    return c.on_run("render", None, "--frame", "99") + (["--frame", "out of range"],)


@case("cli-eval-frame-out-of-range")
def _(c):
    return c.on_run("eval", None, "--frame", "-1") + (["--frame", "out of range"],)


@case("cli-mesh-resolution")
def _(c):
    return c.on_run("mesh", None, "--resolution", "0") + (["--resolution"],)


@case("cli-mesh-out-suffix")
def _(c):
    return c.on_run("mesh", None, "--out", str(c.tmp / "m.xyz")) + (["m.xyz", "--out", ".ply, .obj, .glb, .stl or .off"],)


# --------------------------------------------------------------------------- run folders and checkpoints
@case("run-folder-missing")
def _(c):
    return ["mesh", str(c.tmp / "norun"), "--device", "cpu"], None, ["norun", "run folder not found"]


@case("run-json-missing")
def _(c):
    run = c.run()
    (run / "run.json").unlink()
    return c.on_run("render", run) + (["run.json", "--scene"],)


@case("run-json-malformed")
def _(c):
    run = c.run()
    (run / "run.json").write_text('{"scene": ')
    return c.on_run("eval", run) + (["run.json", "scene"],)


@case("run-json-scene-gone")
def _(c):
    run = c.run()
    (run / "run.json").write_text(json.dumps({"scene": str(c.tmp / "moved")}))
    return c.on_run("mesh", run) + (["run.json", "scene", "moved", "--scene"],)


@case("checkpoint-missing")
def _(c):
    run = c.run()
    (run / "checkpoint.pt").unlink()
    return c.on_run("render", run) + (["checkpoint.pt", "no checkpoint"],)


@case("checkpoint-truncated")
def _(c):
    run = c.run()
    p = run / "checkpoint.pt"
    p.write_bytes(p.read_bytes()[:1000])
    return c.on_run("mesh", run) + (["checkpoint.pt", "unreadable checkpoint"],)


@case("checkpoint-malicious")
def _(c):
    class Payload:
        def __reduce__(self):
            return exec, (f"open({str(c.tmp / 'pwned')!r}, 'w').close()",)
    run = c.run()
    st = torch.load(run / "checkpoint.pt", weights_only=True)
    st["step"] = Payload()
    torch.save(st, run / "checkpoint.pt")
    return c.on_run("eval", run) + (["checkpoint.pt", "refused"],)


@case("checkpoint-missing-entry")
def _(c):
    run = c.run()
    st = torch.load(run / "checkpoint.pt", weights_only=True)
    del st["field"]
    torch.save(st, run / "checkpoint.pt")
    return c.on_run("render", run) + (["checkpoint.pt", "field", "missing entry"],)


@case("checkpoint-other-model")
def _(c):
    run = c.run()
    st = torch.load(run / "checkpoint.pt", weights_only=True)
    st["config"]["log2_table"] = 13  # the weights are a 2^12 table
    torch.save(st, run / "checkpoint.pt")
    return c.on_run("mesh", run) + (["checkpoint.pt", "does not fit"],)


@case("run-finished-without-overwrite")
def _(c):
    return c.train(c.b["fn"], overwrite=False) + (["out_run", "--out", "finished run"],)


@case("run-resume-without-checkpoint")
def _(c):
    out = c.tmp / "half"
    out.mkdir()
    (out / "config.yaml").write_text("steps: 4\n")
    return ["train", str(c.b["fn"]), "--out", str(out), "--resume", "--device", "cpu", *SMALL_RUN], out, \
        ["checkpoint.pt", "--resume"]


# --------------------------------------------------------------------------- the runner
def _snapshot(folder: Path | None) -> dict[str, str]:
    if folder is None or not folder.exists():
        return {}
    if folder.is_file():
        return {folder.name: hashlib.sha1(folder.read_bytes()).hexdigest()}
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(folder.rglob("*"))}


def test_corpus_is_large_enough():
    assert len(CASES) >= 50, len(CASES)


def test_bases_are_valid(bases, tmp_path, capsys):
    """The corpus breaks one thing per case: the unbroken bases load and import cleanly."""
    from fastneus.formats.detect import load_scene

    for kind in ("fn", "an", "neus"):
        assert len(load_scene(bases[kind]).frames) == 3
    c = Ctx(bases, tmp_path)
    for argv, out in (c.import_calib(), c.import_calib(colmap=bases["colmap"])):
        shutil.rmtree(out)
        assert main(argv) == 0, capsys.readouterr().err
        assert len(load_scene(out).frames) == 3


@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input(name, bases, tmp_path, capsys):
    c = Ctx(bases, tmp_path)
    argv, guard, needles = CASES[name](c)
    before = _snapshot(guard)
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    err = capsys.readouterr().err.strip()
    assert rc not in (0, None), f"{name}: accepted"
    assert len(err.splitlines()) == 1, f"{name}: not one line:\n{err}"
    assert "Traceback" not in err and "internal error" not in err, err
    assert "error" in err, err
    for n in needles:
        assert n in err, f"{name}: {n!r} not named in: {err}"
    assert _snapshot(guard) == before, f"{name}: the earlier result in {guard} changed"
    assert not (tmp_path / "pwned").exists()
    assert not [p for p in tmp_path.rglob(".*staging-*")], "staging folder left behind"
