"""No code runs from scene files or checkpoints; run folders are not silently replaced; Ctrl-C
saves a checkpoint that --resume continues.

Each malicious file is first shown to be live (a plain unpickler does run its payload), so
the tests cannot pass vacuously.
"""
from __future__ import annotations

from conftest import one_line_error as _one_line_error

import io
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import SMALL_RUN
from fastneus.cli import main
from fastneus.errors import FastneusError

SAMPLE = Path("/work/shared/data/activeneus_sample")
if not SAMPLE.is_dir():
    SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "activeneus_sample"


class Payload:
    """Unpickling this creates ``marker``: stands for any command an attacker would run."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').close()",)


def _live(marker: Path, load) -> None:
    """Check that ``load()`` with a permissive unpickler runs the payload, then reset."""
    load()
    assert marker.exists(), "test payload is not live"
    marker.unlink()


@pytest.fixture(scope="module")
def an_scene(small_scene, tmp_path_factory):
    """The small scene in the ActiveNeuS format."""
    from fastneus.data import Scene
    from fastneus.formats.activeneus import write_activeneus

    out = tmp_path_factory.mktemp("an") / "scene"
    write_activeneus(Scene.load(small_scene), out)
    return out


def _npz_with(src: Path, dst: Path, **entries) -> Path:
    """Copy scene folder ``src`` to ``dst`` with npz entries replaced (object values are pickled)."""
    shutil.copytree(src, dst)
    with np.load(src / "cameras_sphere.npz", allow_pickle=True) as z:  # our own file: trusted
        d = dict(z)
    d.update(entries)
    np.savez(dst / "cameras_sphere.npz", **d)
    return dst / "cameras_sphere.npz"


# --------------------------------------------------------------------------- scene files
@pytest.mark.parametrize("key", ["illumination_params", "cam_mat_0", "camera_refraction", "projector_refraction"])
def test_pickled_payload_in_npz_does_not_run(an_scene, tmp_path, capsys, key):
    marker = tmp_path / "pwned"
    npz = _npz_with(an_scene, tmp_path / "evil", **{key: np.array(Payload(marker), dtype=object)})
    _live(marker, lambda: np.load(npz, allow_pickle=True)[key])
    assert main(["train", str(npz.parent), "--out", str(tmp_path / "run"), "--device", "cpu"]) == 2
    _one_line_error(capsys, "cameras_sphere.npz", key)
    assert not marker.exists()
    assert not (tmp_path / "run").exists()


def test_payload_inside_the_illumination_dict_does_not_run(an_scene, tmp_path):
    from fastneus.formats.detect import load_scene

    marker = tmp_path / "pwned"
    ip = {"ambient": 1.0, "diffuse": Payload(marker), "emissive": 0.1}
    npz = _npz_with(an_scene, tmp_path / "evil", illumination_params=np.array(ip, dtype=object))
    _live(marker, lambda: np.load(npz, allow_pickle=True)["illumination_params"])
    with pytest.raises(FastneusError, match="refused to unpickle.*builtins.exec"):
        load_scene(npz.parent)
    assert not marker.exists()


def test_payload_inside_a_port_dict_does_not_run_and_a_genuine_port_loads(an_scene, tmp_path):
    from fastneus.formats.detect import load_scene

    marker = tmp_path / "pwned"
    port = {"normal": [0.0, Payload(marker)], "depth": 0.1, "mu": 1.33}
    npz = _npz_with(an_scene, tmp_path / "evil", camera_refraction=np.array(port, dtype=object))
    _live(marker, lambda: np.load(npz, allow_pickle=True)["camera_refraction"])
    with pytest.raises(FastneusError, match="camera_refraction"):
        load_scene(npz.parent)
    assert not marker.exists()
    # the official layout: a pickled dict of numbers and a list of two numbers
    ok = {"normal": [np.float64(0.0), 0.1], "depth": np.float32(0.05), "mu": 1.33}
    npz = _npz_with(an_scene, tmp_path / "good", camera_refraction=np.array(ok, dtype=object))
    cam = next(iter(load_scene(npz.parent).cameras.values()))
    assert cam.port is not None and cam.port.n_water == pytest.approx(1.33)


def test_payload_in_unused_entry_is_never_unpickled(an_scene, tmp_path):
    """``aabb`` is pickled in the official format but unused: the scene loads, the payload stays inert."""
    from fastneus.formats.detect import load_scene

    marker = tmp_path / "pwned"
    npz = _npz_with(an_scene, tmp_path / "evil", aabb=np.array(Payload(marker), dtype=object))
    _live(marker, lambda: np.load(npz, allow_pickle=True)["aabb"])
    assert len(load_scene(npz.parent).frames) == 3
    assert not marker.exists()


def test_official_sample_and_numpy_scalar_dicts_still_load(an_scene, tmp_path):
    from fastneus.formats.activeneus import read_activeneus
    from fastneus.formats.safe_npz import open_npz, read_number_dict

    il = read_activeneus(SAMPLE).illumination
    assert (il.ambient, il.i_r, il.i_b) == (1.0, 0.4, 0.1)
    # numpy scalars as values, pickled by this numpy (numpy._core) and as numpy 1.x wrote them (numpy.core)
    ip = np.array({"ambient": np.float64(1.0), "diffuse": np.float32(0.25), "emissive": np.int64(0)}, dtype=object)
    npz = _npz_with(an_scene, tmp_path / "np2", illumination_params=ip)
    got = read_number_dict(open_npz(npz), "illumination_params", npz)
    assert got == {"ambient": 1.0, "diffuse": 0.25, "emissive": 0.0}
    assert read_activeneus(npz.parent).illumination.i_r == 0.25
    buf = io.BytesIO()
    np.save(buf, ip)
    raw = buf.getvalue()
    h = raw.index(b"\x80")  # protocol-3 pickle: GLOBAL opcodes name modules as newline-terminated text
    old = raw[:h] + pickle.dumps(ip, protocol=3).replace(b"numpy._core.", b"numpy.core.")
    assert b"numpy.core.multiarray\nscalar" in old
    import zipfile

    with zipfile.ZipFile(npz, "a") as zf:
        zf.writestr("legacy.npy", old)
    assert read_number_dict(open_npz(npz), "legacy", npz) == got


@pytest.mark.parametrize("value,needle", [
    (np.array([{"ambient": 1.0}], dtype=object), "shape (1,)"),
    (np.array(["a", "b"], dtype=object), "shape (2,)"),
    (np.array({"ambient": 1.0, "diffuse": "0.4", "emissive": 0.1}, dtype=object), "illumination_params.diffuse"),
    (np.array({"ambient": 1.0, "diffuse": np.float64("nan"), "emissive": 0.1}, dtype=object), "finite"),
    (np.array({"ambient": 1.0, "emissive": 0.1}, dtype=object), "illumination_params.diffuse"),
    (np.array(0.4), "expected a dict"),
    (np.array({"ambient": 1.0, "diffuse": np.array([0.4]), "emissive": 0.1}, dtype=object), "got an array"),
])
def test_illumination_params_that_are_not_a_number_dict(an_scene, tmp_path, value, needle):
    from fastneus.formats.detect import load_scene

    npz = _npz_with(an_scene, tmp_path / "bad", illumination_params=value)
    with pytest.raises(FastneusError, match="illumination_params") as e:
        load_scene(npz.parent)
    assert needle in str(e.value)


# --------------------------------------------------------------------------- checkpoints
@pytest.fixture(scope="module")
def small_run(small_scene, tmp_path_factory):
    """A run folder with a checkpoint (no training needed), run.json and an earlier mesh."""
    from fastneus.config import load_config
    from fastneus.formats.detect import load_scene
    from fastneus.train.trainer import Trainer

    run = tmp_path_factory.mktemp("run") / "r"
    tr = Trainer(load_scene(small_scene), load_config("cpu-quick", SMALL_RUN), run, "cpu")
    tr.save()
    (run / "run.json").write_text(json.dumps({"scene": str(small_scene)}))
    (run / "mesh.ply").write_text("earlier result\n")
    return run


def test_checkpoint_is_plain_data_and_round_trips(small_run, tmp_path):
    from fastneus.train.checkpoint import CKPT_NAME, load_checkpoint, plain

    st = torch.load(small_run / CKPT_NAME, weights_only=True)  # torch's restricted unpickler accepts it
    assert st["step"] == 0 and isinstance(st["field"], dict) and isinstance(st["gen"], torch.Tensor)
    assert load_checkpoint(small_run)["config"]["hashgrid"]["log2_table"] == 12
    assert plain({"a": np.float32(2.0), "b": (np.arange(3), [np.int64(1)])})["b"][1] == [1]
    with pytest.raises(TypeError, match="state.x"):
        plain({"x": Path(".")})


@pytest.mark.parametrize("verb", ["mesh", "render", "eval", "resume"])
def test_malicious_checkpoint_does_not_run(small_run, small_scene, tmp_path, capsys, verb):
    from fastneus.train.checkpoint import CKPT_NAME

    run = tmp_path / "run"
    shutil.copytree(small_run, run)
    marker = tmp_path / "pwned"
    st = torch.load(run / CKPT_NAME, weights_only=True)
    st["extra"] = Payload(marker)
    torch.save(st, run / CKPT_NAME)
    _live(marker, lambda: torch.load(run / CKPT_NAME, weights_only=False))
    before = (run / CKPT_NAME).read_bytes()
    argv = {"mesh": ["mesh", str(run), "--resolution", "16"], "render": ["render", str(run)],
            "eval": ["eval", str(run)],
            "resume": ["train", str(small_scene), "--out", str(run), "--resume"] + SMALL_RUN}[verb]
    assert main(argv + ["--device", "cpu"]) == 2
    _one_line_error(capsys, CKPT_NAME, "refused")
    assert not marker.exists()
    assert (run / CKPT_NAME).read_bytes() == before and (run / "mesh.ply").read_text() == "earlier result\n"


# --------------------------------------------------------------------------- run folders
def test_finished_run_is_not_overwritten(small_scene, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu"] + SMALL_RUN) == 0
    capsys.readouterr()
    metrics = (run / "metrics.json").read_bytes()
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu"] + SMALL_RUN) == 2
    _one_line_error(capsys, str(run), "--overwrite", "finished run")
    assert (run / "metrics.json").read_bytes() == metrics
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu", "--overwrite", "--resume"]) == 2
    _one_line_error(capsys, "--overwrite")
    # --overwrite starts again: the old log is replaced, not appended to
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu", "--overwrite"] + SMALL_RUN) == 0
    log = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == sorted({r["step"] for r in log})
    (run / "metrics.json").unlink()  # an unfinished run (checkpoint only) is refused too
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu"] + SMALL_RUN) == 2
    _one_line_error(capsys, "unfinished run", "--resume")
    other = tmp_path / "docs"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert main(["train", str(small_scene), "--out", str(other), "--device", "cpu"] + SMALL_RUN) == 2
    _one_line_error(capsys, "not a fastneus run", "notes.txt")


# --------------------------------------------------------------------------- Ctrl-C
def test_ctrl_c_saves_a_checkpoint_that_resume_continues(small_scene, tmp_path, capsys):
    from fastneus.train.checkpoint import load_checkpoint

    run = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "fastneus.cli", "train", str(small_scene), "--out", str(run), "--device", "cpu",
           *SMALL_RUN, "steps=100000", "save_every=100000"]
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        t0 = time.time()
        while not ((run / "log.jsonl").is_file() and (run / "log.jsonl").read_text().count("\n") >= 3):
            assert p.poll() is None and time.time() - t0 < 120, "training did not start"
            time.sleep(0.1)
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    line = err.strip()
    assert len(line.splitlines()) == 1 and "Traceback" not in line, err
    assert "interrupted: SIGINT at step" in line and "--resume" in line and "checkpoint.pt" in line
    step = load_checkpoint(run)["step"]
    assert step >= 3 and f"step {step};" in line
    assert not (run / "metrics.json").exists()
    # a fresh start there is refused; --resume continues from the saved step and finishes the run
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu"] + SMALL_RUN) == 2
    capsys.readouterr()
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu", "--resume",
                 *SMALL_RUN, f"steps={step + 3}"]) == 0
    assert load_checkpoint(run)["step"] == step + 3
    assert json.loads((run / "metrics.json").read_text())["steps"] == step + 3


# --------------------------------------------------------------------------- masks
def test_empty_masks(small_scene, tmp_path):
    import cv2

    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    scene_dir = tmp_path / "scene"
    shutil.copytree(small_scene, scene_dir)
    sc = Scene.load(scene_dir)
    blank = np.zeros((24, 24), np.uint8)
    cv2.imwrite(str(sc.path(sc.frames[1].mask)), blank)
    cfg = load_config("cpu-quick", SMALL_RUN)
    tr = Trainer(sc, cfg, tmp_path / "r1", "cpu")
    assert tr.masks_used and "warning: empty (all-zero) mask" in tr.masks_note and "001" in tr.masks_note
    for f in sc.frames:
        cv2.imwrite(str(sc.path(f.mask)), blank)
    with pytest.raises(FastneusError, match=r"frames\[0\]\.mask: mask is empty"):
        Trainer(sc, cfg, tmp_path / "r2", "cpu")
