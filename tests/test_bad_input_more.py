"""More bad input (issue 20 items 5, 6, 9, 10): inputs that hung, ended as an "internal error",
or were accepted and silently trained something wrong.

One table of crafted inputs (built from the corpus's valid bases in ``tests/test_bad_input_corpus.py``)
run through the CLI in-process: each must exit 2 with exactly one line on stderr naming the file
and/or field at fault, and leave the output folder as it was. A few behaviours that are not a
refusal (EXIF orientation, JSON without NaN, a full disk) have their own tests below.
"""
from __future__ import annotations

import errno
import json
import shutil
import struct
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
import torch

from fastneus.cli import main
from test_bad_input_corpus import Ctx, _calib, _colmap, _snapshot, bases  # noqa: F401 - bases is a fixture

CASES: dict[str, Callable] = {}


def case(name: str):
    def reg(fn):
        assert name not in CASES
        CASES[name] = fn
        return fn
    return reg


def _yaml(c, text: str, name: str = "my.yaml") -> str:
    p = c.tmp / name
    p.write_text(text)
    return str(p)


def _ckpt(c, edit: Callable[[dict], None]) -> Path:
    """A copy of the base run whose checkpoint is edited by ``edit``."""
    run = c.run()
    st = torch.load(run / "checkpoint.pt", weights_only=True)
    edit(st)
    torch.save(st, run / "checkpoint.pt")
    return run


# --------------------------------------------------------------------------- item 5: unpickler work bound
@case("an-illumination-shared-references")
def _(c):
    leaf = [1.0]
    for _ in range(6):  # ~1 KB of pickle, 64^6 leaves when walked naively
        leaf = [leaf] * 64
    ip = np.array({"ambient": leaf, "diffuse": 0.4, "emissive": 0.1}, dtype=object)
    return c.train(c.npz("an", illumination_params=ip)) + (["cameras_sphere.npz", "illumination_params", "refused"],)


# --------------------------------------------------------------------------- item 9: scene.json
def _raw_json(c, text: str | bytes) -> Path:
    d = c.copy("fn")
    (d / "scene.json").write_bytes(text.encode() if isinstance(text, str) else text)
    return d


def _K(d: dict, row: int, col: int, v) -> None:
    d["cameras"]["cam0"]["K"][row][col] = v


@case("json-width-nan")
def _(c):
    return c.train(c.json(lambda d: d["cameras"]["cam0"].update(width=float("nan")))) + \
        (["scene.json", "cameras.cam0.width"],)


@case("json-height-infinity")
def _(c):
    return c.train(c.json(lambda d: d["cameras"]["cam0"].update(height=float("inf")))) + \
        (["scene.json", "cameras.cam0.height"],)


@case("json-width-huge")
def _(c):
    return c.train(c.json(lambda d: d["cameras"]["cam0"].update(width=1e300))) + (["scene.json", "cameras.cam0.width"],)


@case("json-view-nan")
def _(c):
    return c.train(c.json(lambda d: d["frames"][1].update(view=float("nan")))) + (["scene.json", "frames[1].view"],)


@case("json-nested-deep")
def _(c):
    return c.train(_raw_json(c, "[" * 200_000 + "]" * 200_000)) + (["scene.json", "nested"],)


@case("json-not-utf8")
def _(c):
    return c.train(_raw_json(c, b'{"format": "\xff\xfe"}')) + (["scene.json", "UTF-8"],)


@case("png-header-more-pixels-than-opencv-decodes")
def _(c):
    def edit(d):
        qid = d["frames"][0]["projectors"]["proj0"]["pattern"]
        d["projectors"]["proj0"].update(width=40000, height=40000)
        head = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">IIBBBBB", 40000, 40000, 8, 2, 0, 0, 0)
        c.fn_file(d["patterns"][qid]["file"]).write_bytes(head + b"\x00" * 64)
    return c.train(c.json(edit)) + (["scene.json", "patterns.", "40000x40000"],)


# --------------------------------------------------------------------------- item 10: scene.json accepted, trained wrong
@case("json-principal-point-far-outside")
def _(c):
    return c.train(c.json(lambda d: _K(d, 0, 2, 1e6))) + (["scene.json", "cameras.cam0.K", "principal point"],)


@case("json-projector-principal-point-far-outside")
def _(c):
    return c.train(c.json(lambda d: d["projectors"]["proj0"]["K"][1].__setitem__(2, -1e5))) + \
        (["scene.json", "projectors.proj0.K", "principal point"],)


@case("json-i_r-negative")
def _(c):
    return c.train(c.json(lambda d: d["illumination"].update(i_r=-0.4))) + (["scene.json", "illumination.i_r"],)


@case("json-ambient-negative")
def _(c):
    return c.train(c.json(lambda d: d["illumination"].update(ambient=-1))) + (["scene.json", "illumination.ambient"],)


@case("json-radius-huge")
def _(c):
    return c.train(c.json(lambda d: d["bounds"].update(radius=1e300))) + (["scene.json", "bounds.radius"],)


@case("json-radius-tiny")
def _(c):
    return c.train(c.json(lambda d: d["bounds"].update(radius=1e-300))) + (["scene.json", "bounds.radius"],)


@case("json-same-photo-through-symlink")
def _(c):
    def edit(d):
        c.fn_file("images/again.png").symlink_to(c.fn_file(d["frames"][0]["image"]))
        d["frames"][2]["image"] = "images/again.png"
    return c.train(c.json(edit)) + (["scene.json", "frames[2].image", "frames[0]"],)


@case("json-same-photo-hardlink")
def _(c):
    def edit(d):
        c.fn_file("images/again.png").hardlink_to(c.fn_file(d["frames"][1]["image"]))
        d["frames"][2]["image"] = "images/again.png"
    return c.train(c.json(edit)) + (["scene.json", "frames[2].image", "frames[1]"],)


# --------------------------------------------------------------------------- npz scenes
@case("an-complex-matrix")
def _(c):
    return c.train(c.npz("an", cam_mat_0=c.npz_value("an", "cam_mat_0") + 1e-3j)) + \
        (["cameras_sphere.npz", "cam_mat_0", "complex"],)


@case("neus-complex-matrix")
def _(c):
    return c.train(c.npz("neus", world_mat_1=c.npz_value("neus", "world_mat_1") * (1 + 0j))) + \
        (["cameras_sphere.npz", "world_mat_1", "complex"],)


# --------------------------------------------------------------------------- NeRF transforms.json
def _nerf(c, edit: Callable[[dict], None] | None = None, raw: bytes | None = None) -> Path:
    from fastneus.data import Scene
    from fastneus.formats.nerf import write_nerf

    d = c.tmp / "nerf"
    if not d.exists():
        write_nerf(Scene.load(c.b["fn"]), d)
    p = d / "transforms.json"
    if raw is not None:
        p.write_bytes(raw)
    else:
        data = json.loads(p.read_text())
        edit(data)
        p.write_text(json.dumps(data))
    return d


@case("nerf-w-nan")
def _(c):
    def edit(d):
        for f in d["frames"]:
            f.pop("w", None)
        d["w"] = float("nan")
    return c.train(_nerf(c, edit)) + (["transforms.json", ".w"],)


@case("nerf-h-infinity")
def _(c):
    def edit(d):
        for f in d["frames"]:
            f.pop("h", None)
        d["h"] = float("inf")
    return c.train(_nerf(c, edit)) + (["transforms.json", ".h"],)


@case("nerf-nested-deep")
def _(c):
    return c.train(_nerf(c, raw=b'{"a":' + b"[" * 200_000)) + (["transforms.json", "nested"],)


@case("nerf-not-utf8")
def _(c):
    return c.train(_nerf(c, raw=b'{"frames": "\xc3\x28"}')) + (["transforms.json", "UTF-8"],)


@case("nerf-image-header-huge")
def _(c):
    def edit(d):
        for f in d["frames"]:
            f.pop("w", None), f.pop("h", None)
        d.pop("w", None), d.pop("h", None)
        img = c.tmp / "nerf" / d["frames"][0]["file_path"]
        head = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">IIBBBBB", 100000, 100000, 8, 2, 0, 0, 0)
        img.write_bytes(head + b"\x00" * 64)
    return c.train(_nerf(c, edit)) + (["transforms.json", "100000"],)


# --------------------------------------------------------------------------- import-calib, COLMAP, lasers, convert
@case("calib-principal-point-far-outside")
def _(c):
    K = np.array([[30.0, 0, 1e6], [0, 30.0, 11.5], [0, 0, 1]])
    return c.import_calib(_calib(c, cam_K=K)) + (["c.yml", "cam_K", "principal point", "!staging"],)


@case("calib-image-header-huge")
def _(c):
    imgs = c.tmp / "imgs"
    shutil.copytree(c.b["images"], imgs)
    head = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">IIBBBBB", 100000, 100000, 8, 2, 0, 0, 0)
    (imgs / "000.png").write_bytes(head + b"\x00" * 64)
    return c.import_calib(images=imgs) + (["000.png", "!staging"],)


@case("calib-pattern-header-huge")
def _(c):
    pat = c.tmp / "pattern.png"
    head = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">IIBBBBB", 100000, 100000, 8, 2, 0, 0, 0)
    pat.write_bytes(head + b"\x00" * 64)
    return c.import_calib(pattern=pat) + (["pattern.png", "--patterns", "!staging"],)


@case("calib-size-nan")
def _(c):
    return c.import_calib(_calib(c, cam_width=np.array([[np.nan]]), cam_height=np.array([[24.0]]))) + \
        (["c.yml", "cam_width"],)


@case("calib-size-infinity")
def _(c):
    return c.import_calib(_calib(c, proj_size=np.array([[np.inf, 48.0]]))) + (["c.yml", "proj_size"],)


@case("poses-nested-deep")
def _(c):
    p = c.tmp / "poses.json"
    p.write_text("[" * 200_000)
    return c.import_calib(poses=p) + (["poses.json", "nested"],)


@case("poses-not-utf8")
def _(c):
    p = c.tmp / "poses.json"
    p.write_bytes(b'{"frames": "\xff"}')
    return c.import_calib(poses=p) + (["poses.json", "UTF-8"],)


def _lasers(c, text: str | bytes) -> list[str]:
    p = c.tmp / "lasers.yaml"
    p.write_bytes(text.encode() if isinstance(text, str) else text)
    return ["--laser-planes", str(p)]


_PLANE = "lasers:\n  l0:\n    planes:\n      - {normal: [1, 0, 0], offset: 0, width: 1.0}\n"


@case("lasers-units-list")
def _(c):
    return c.import_calib(None, None, None, None, None, *_lasers(c, "units: [mm]\n" + _PLANE)) + \
        (["lasers.yaml", "units"],)


@case("lasers-not-utf8")
def _(c):
    return c.import_calib(None, None, None, None, None, *_lasers(c, b"units: \xff\n")) + (["lasers.yaml"],)


@case("import-calib-bounds-nan")
def _(c):
    return c.import_calib(None, None, None, None, None, "--bounds", "nan,0,0,1") + (["--bounds"],)


@case("import-calib-bounds-radius-inf")
def _(c):
    return c.import_calib(None, None, None, None, None, "--bounds", "0,0,0,inf") + (["--bounds"],)


@case("import-calib-bounds-radius-huge")
def _(c):
    return c.import_calib(None, None, None, None, None, "--bounds", "0,0,0,1e300") + (["--bounds", "bounds radius", "!staging"],)


@case("import-calib-colmap-scale-nan")
def _(c):
    return c.import_calib(None, None, None, None, c.b["colmap"], "--colmap-scale", "nan") + (["--colmap-scale"],)


@case("convert-downscale-too-large")
def _(c):
    out = c.scene_out()
    return ["convert", str(c.b["fn"]), "--to", "activeneus", "--downscale", "100", "--out", str(out)], out, \
        ["--downscale", "24x24"]


# --------------------------------------------------------------------------- configs
@case("config-yaml-integer-key")
def _(c):
    return c.train(c.b["fn"], "--config", _yaml(c, "1: 2\n")) + (["my.yaml", "1"],)


@case("config-yaml-not-utf8")
def _(c):
    p = c.tmp / "my.yaml"
    p.write_bytes(b"steps: \xff\n")
    return c.train(c.b["fn"], "--config", str(p)) + (["my.yaml"],)


@case("config-yaml-nested-deep")
def _(c):
    return c.train(c.b["fn"], "--config", _yaml(c, "steps: " + "[" * 50_000)) + (["my.yaml"],)


@case("config-frames-nested-list")
def _(c):
    return c.train(c.b["fn"], "frames=[[1]]") + (["command line", "frames"],)


@case("config-frames-infinity")
def _(c):
    return c.train(c.b["fn"], "frames=[.inf]") + (["command line", "frames"],)


@case("config-frames-bool")
def _(c):
    return c.train(c.b["fn"], "frames=[true]") + (["command line", "frames"],)


def _cfg_case(name: str, override: str, key: str, *more: str):
    @case(f"config-{name}")
    def _(c):
        return c.train(c.b["fn"], override) + (["command line", key, *more],)


for _n, _o, _k in (("log2_table-31", "log2_table=31", "log2_table"), ("log2_table-40", "log2_table=40", "log2_table"),
                   ("features-9", "features=9", "features"), ("seed-negative", "seed=-1", "seed"),
                   ("seed-2^70", f"seed={2 ** 70}", "seed"), ("threads-1e20", "threads=1e20", "threads"),
                   ("variance_init-100", "variance_init=100", "variance_init"),
                   ("sdf_layers-negative", "sdf_layers=-3", "sdf_layers"),
                   ("color_layers-negative", "color_layers=-1", "color_layers"),
                   ("base_res-above-finest", "base_res=4096", "base_res"),
                   ("eikonal_weight-negative", "eikonal_weight=-1", "eikonal_weight"),
                   ("steps-huge", f"steps={2 ** 63}", "steps"),
                   ("init_radius-2", "init_radius=2", "init_radius")):
    _cfg_case(_n, _o, _k)


@case("config-yaml-threads-huge")
def _(c):  # a float in YAML: not FASTNEUS_THREADS's fault (unset here)
    return c.train(c.b["fn"], "--config", _yaml(c, "threads: 1.0e+20\n")) + (["my.yaml", "threads", "!FASTNEUS_THREADS"],)


@case("config-yaml-huge-integer")
def _(c):
    return c.train(c.b["fn"], "--config", _yaml(c, "seed: " + "9" * 5000 + "\n")) + (["my.yaml"],)


def test_yaml_off_is_off(tmp_path):
    """YAML 1.1 reads ``masks: off`` as false; for an on/off key it means 'off', not an error about 'False'."""
    from fastneus.config import load_config

    p = tmp_path / "c.yaml"
    p.write_text("masks: off\nbg_prior: yes\nmedium: no\n")
    cfg = load_config(str(p))
    assert (cfg.loss.masks, cfg.loss.bg_prior, cfg.rig.medium) == ("off", "on", "off")


# --------------------------------------------------------------------------- checkpoints
@case("run-json-nested-deep")
def _(c):
    run = c.run()
    (run / "run.json").write_text('{"scene": ' + "[" * 200_000)
    return c.on_run("render", run) + (["run.json", "scene"],)


@case("checkpoint-config-steps-string")
def _(c):
    return c.on_run("mesh", _ckpt(c, lambda st: st["config"].update(steps="many"))) + (["checkpoint.pt", "steps"],)


@case("checkpoint-config-legacy-list")
def _(c):
    return c.on_run("render", _ckpt(c, lambda st: st["config"].update(warmup_steps=[1, 2]))) + \
        (["checkpoint.pt", "warmup_steps"],)


@case("checkpoint-config-legacy-per-level-string")
def _(c):
    return c.on_run("render", _ckpt(c, lambda st: st["config"].update(c2f_steps_per_level="x"))) + \
        (["checkpoint.pt", "c2f_steps_per_level"],)


@case("checkpoint-config-integer-key")
def _(c):
    return c.on_run("mesh", _ckpt(c, lambda st: st["config"].update({7: 1}))) + (["checkpoint.pt", "7"],)


@case("checkpoint-config-seed-huge")
def _(c):
    return c.on_run("mesh", _ckpt(c, lambda st: st["config"].update(seed=2 ** 70))) + (["checkpoint.pt", "seed"],)


@case("checkpoint-nan-weights")
def _(c):
    def edit(st):
        st["field"]["table"].view(-1)[5] = float("nan")
    return c.on_run("mesh", _ckpt(c, edit)) + (["checkpoint.pt", "field.table", "non-finite"],)


@case("checkpoint-inf-illumination")
def _(c):
    return c.on_run("eval", _ckpt(c, lambda st: st["log_ir"].fill_(float("inf")))) + \
        (["checkpoint.pt", "log_ir", "non-finite"],)


# --------------------------------------------------------------------------- item 6: EXIF orientation
def _jpeg_with_orientation(bgr: np.ndarray, orientation: int, big_endian: bool = False) -> bytes:
    """A JPEG whose APP1 Exif block holds only IFD0 with the Orientation tag (as a phone writes)."""
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    e = ">" if big_endian else "<"
    tiff = (b"MM" if big_endian else b"II") + struct.pack(e + "HI", 42, 8)
    ifd = struct.pack(e + "H", 1) + struct.pack(e + "HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack(e + "I", 0)
    payload = b"Exif\x00\x00" + tiff + ifd
    data = buf.tobytes()
    return data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:]


def test_exif_orientation_is_ignored_with_a_warning(small_scene, tmp_path, capsys):
    """A photo tagged "rotate 90" is read as stored (as the size check, the masks and the intrinsics
    see it), and one warning line names the file."""
    from fastneus.data import Scene
    from fastneus.data.images import exif_orientation

    d = tmp_path / "s"
    shutil.copytree(small_scene, d)
    bgr = np.zeros((24, 24, 3), np.uint8)
    bgr[:, :12] = (0, 0, 255)  # left half red, right half blue: a rotation moves them
    bgr[:, 12:] = (255, 0, 0)
    (d / "images" / "000.jpg").write_bytes(_jpeg_with_orientation(bgr, 6))
    (d / "images" / "001.jpg").write_bytes(_jpeg_with_orientation(bgr, 1, big_endian=True))
    data = json.loads((d / "scene.json").read_text())
    data["frames"][0]["image"] = "images/000.jpg"
    data["frames"][1]["image"] = "images/001.jpg"
    (d / "scene.json").write_text(json.dumps(data))
    capsys.readouterr()
    scene = Scene.load(d)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "000.jpg" in err[0] and "orientation 6" in err[0], err
    stored = cv2.imread(str(d / "images" / "000.jpg"), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)[:, :, ::-1]
    np.testing.assert_array_equal(scene.image(0), stored)
    assert scene.image(0)[12, 2, 0] > 200 and scene.image(0)[12, 21, 2] > 200  # red left, blue right
    assert exif_orientation(d / "images" / "001.jpg") == 1
    assert exif_orientation(d / "images" / "002.png") is None
    assert exif_orientation(d / "scene.json") is None
    Scene.load(d)  # warned once per file
    assert capsys.readouterr().err == ""


def test_colmap_quaternion_of_huge_components(tmp_path):
    """A quaternion is normalised: components of 1e200 (whose norm overflows to inf) are the same rotation."""
    from fastneus.formats.colmap import read_images_txt

    for q in ("1e200 0 0 1e200", "0.7071067811865476 0 0 0.7071067811865476", "1e-200 0 0 1e-200"):
        (tmp_path / "images.txt").write_text(f"1 {q} 0 0 1 1 a.png\n\n")
        T = read_images_txt(tmp_path / "images.txt")["a.png"].world_to_cam
        np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


# --------------------------------------------------------------------------- item 9: a full disk
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_full_disk_during_resume_says_no_space(bases, tmp_path, capsys, monkeypatch):  # noqa: F811
    """Every checkpoint write hits a full disk (/dev/full): one line naming the checkpoint and
    "No space left on device", not torch's "[enforce fail at inline_container.cc]"."""
    import fastneus.train.checkpoint as ck

    run = Ctx(bases, tmp_path).run()
    before = (run / "checkpoint.pt").read_bytes()
    monkeypatch.setattr(ck, "atomic_write", lambda path, write: write("/dev/full"))
    rc = main(["train", str(bases["fn"]), "--out", str(run), "--resume", "--device", "cpu", "steps=6"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "checkpoint.pt" in err[0] and "No space left on device" in err[0] and "enforce" not in err[0], err
    assert (run / "checkpoint.pt").read_bytes() == before


def test_torch_writer_failure_is_an_os_error(tmp_path, monkeypatch):
    """torch's own writer (a path, not a file object) reports a full disk as a RuntimeError: it is
    mapped to an OSError naming the checkpoint (ENOSPC when the disk is nearly full)."""
    import fastneus.train.checkpoint as ck

    def fail(obj, f, *a, **k):
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")

    monkeypatch.setattr(torch, "save", fail)
    monkeypatch.setattr(ck.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(100, 100, 0))
    with pytest.raises(OSError) as e:
        ck.save_checkpoint({"w": torch.zeros(3)}, tmp_path / "checkpoint.pt")
    assert e.value.errno == errno.ENOSPC and e.value.filename.endswith("checkpoint.pt")
    assert not list(tmp_path.iterdir())


def test_threads_error_names_the_key_when_the_variable_is_unset(monkeypatch):
    from fastneus.errors import FastneusError
    from fastneus.kernels import _warp
    from fastneus.train.trainer import _configure_threads

    monkeypatch.delenv("FASTNEUS_THREADS", raising=False)
    before = _warp._threads
    try:
        with pytest.raises(FastneusError) as e:
            _configure_threads(2 ** 40)  # torch refuses it (the config's range check stops it earlier)
    finally:
        _warp._threads = before
    assert e.value.field == "threads"


# --------------------------------------------------------------------------- item 10: eval's output and Ctrl-C
def _strict(text: str):
    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)


def test_metrics_json_never_holds_infinity(bases, tmp_path, capsys, monkeypatch):  # noqa: F811
    """A metric that comes out infinite or NaN (e.g. PSNR of a perfect or an empty render) is
    written as null: metrics.json and eval's printout stay strict JSON."""
    import fastneus.eval.metrics as ev
    from fastneus.io import json_text

    run = Ctx(bases, tmp_path).run()
    monkeypatch.setattr(ev, "image_metrics", lambda scene, renders: {"psnr_pattern": float("inf"),
                                                                     "psnr_texture": np.float32("nan")})
    capsys.readouterr()
    assert main(["eval", str(run), "--device", "cpu", "--resolution", "16"]) == 0
    out = capsys.readouterr().out
    printed = _strict(out[out.index("{"):])
    saved = _strict((run / "metrics.json").read_text())
    assert saved["psnr_pattern"] is None and saved["psnr_texture"] is None and printed["psnr_pattern"] is None
    assert _strict((run / "run.json").read_text())
    assert _strict(json_text({"a": [float("-inf"), 1.5], "b": np.float64(2)})) == {"a": [None, 1.5], "b": 2.0}


def test_ctrl_c_during_eval_says_what_is_kept(bases, tmp_path, capsys, monkeypatch):  # noqa: F811
    import fastneus.pipeline as pl

    run = Ctx(bases, tmp_path).run()
    before = (run / "checkpoint.pt").read_bytes()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pl, "finish_run", interrupted)
    assert main(["eval", str(run), "--device", "cpu"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "checkpoint is untouched" in err[0] and "half-written" in err[0], err
    assert (run / "checkpoint.pt").read_bytes() == before


# --------------------------------------------------------------------------- the runner
@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input(name, bases, tmp_path, capsys):  # noqa: F811 - bases is the imported fixture
    c = Ctx(bases, tmp_path)
    argv, guard, needles = CASES[name](c)
    before = _snapshot(guard)
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    err = capsys.readouterr().err.strip()
    assert rc == 2, f"{name}: exit {rc}:\n{err}"
    assert len(err.splitlines()) == 1, f"{name}: not one line:\n{err}"
    assert "Traceback" not in err and "internal error" not in err, err
    for n in needles:  # "!text": must not appear
        assert (n[1:] not in err) if n.startswith("!") else (n in err), f"{name}: {n!r} in: {err}"
    assert _snapshot(guard) == before, f"{name}: the earlier result in {guard} changed"
    assert not [p for p in tmp_path.rglob(".*staging-*")], "staging folder left behind"
