"""Run folders under hostile or careless use (issue 20): no write through a symbolic link,
--overwrite replaces fastneus's own files only and only after every input is checked, one
writer at a time, a torn log line tolerated, --resume continues with the run's own config.

Each run is a handful of steps on the 24x24 three-view sphere (conftest.small_scene).
"""
from __future__ import annotations

from conftest import one_line_error as _one_line_error

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import SMALL_RUN
from fastneus.cli import main


def _snapshot(folder: Path) -> dict:
    """Every entry below ``folder`` (links not followed) -> its bytes, link target or "dir"."""
    snap = {}
    for root, dirs, files in os.walk(folder):
        for n in dirs + files:
            p = Path(root) / n
            snap[str(p.relative_to(folder))] = (f"link:{os.readlink(p)}" if p.is_symlink() else
                                                "dir" if p.is_dir() else p.read_bytes())
    return snap


def _train(scene, out, *extra) -> int:
    return main(["train", str(scene), "--out", str(out), "--device", "cpu", *extra])


@pytest.fixture(scope="module")
def finished(small_scene, tmp_path_factory):
    """A finished 4-step run (SMALL_RUN); tests copy it."""
    run = tmp_path_factory.mktemp("finished") / "run"
    assert _train(small_scene, run, *SMALL_RUN) == 0
    return run


@pytest.fixture
def run(finished, tmp_path):
    dst = tmp_path / "run"
    shutil.copytree(finished, dst, symlinks=True)
    return dst


@pytest.fixture
def sentinel(tmp_path):
    """A folder outside every output folder, with files a redirected write would replace."""
    s = tmp_path / "elsewhere"
    s.mkdir()
    (s / "log.jsonl").write_text("mine\n")
    (s / "000_color.png").write_bytes(b"my picture")
    (s / "mine.txt").write_text("keep")
    return s


# --------------------------------------------------------------------------- symbolic links (item 2)
def test_resume_does_not_append_through_a_log_symlink(run, small_scene, sentinel, capsys):
    (run / "log.jsonl").unlink()
    (run / "log.jsonl").symlink_to(sentinel / "log.jsonl")
    before = _snapshot(sentinel)
    capsys.readouterr()
    assert _train(small_scene, run, "--resume", "steps=6") == 2
    _one_line_error(capsys, "log.jsonl", "symbolic link")
    assert _snapshot(sentinel) == before


@pytest.mark.parametrize("verb,name", [("render", "renders"), ("mesh", "mesh.ply"), ("eval", "metrics.json"),
                                       ("eval", "report.html"), ("eval", "renders")])
def test_verbs_do_not_write_through_symlinks_in_the_run(run, sentinel, capsys, verb, name):
    p = run / name
    shutil.rmtree(p) if p.is_dir() else p.unlink()
    p.symlink_to(sentinel if name == "renders" else sentinel / "mine.txt")
    before = _snapshot(sentinel)
    argv = {"render": ["render", str(run)], "mesh": ["mesh", str(run), "--resolution", "16"],
            "eval": ["eval", str(run), "--resolution", "16"]}[verb]
    capsys.readouterr()
    assert main(argv + ["--device", "cpu"]) == 2
    _one_line_error(capsys, name, "symbolic link")
    assert _snapshot(sentinel) == before
    assert p.is_symlink()  # refused, not replaced either


def test_a_run_folder_named_through_a_symlink_is_fine(run, tmp_path):
    link = tmp_path / "link"
    link.symlink_to(run)
    assert main(["render", str(link), "--device", "cpu"]) == 0  # the folder the user named may be a link
    assert (run / "renders" / "000_color.png").is_file()


# --------------------------------------------------------------------------- --overwrite (items 3, 4)
def test_overwrite_never_replaces_a_users_files(small_scene, tmp_path, capsys):
    mine = tmp_path / "mine"
    (mine / "renders").mkdir(parents=True)
    (mine / "renders" / "holiday.png").write_bytes(b"png")
    (mine / "mesh.ply").write_text("my scan")
    (mine / "notes.txt").write_text("notes")
    before = _snapshot(mine)
    for extra in ((), ("--overwrite",)):
        assert _train(small_scene, mine, *SMALL_RUN, *extra) == 2
        _one_line_error(capsys, str(mine), "did not write")
        assert _snapshot(mine) == before
    # a folder holding only other files takes a run next to them, and keeps them through --overwrite
    (mine / "mesh.ply").unlink()
    shutil.rmtree(mine / "renders")
    assert _train(small_scene, mine, *SMALL_RUN, "--overwrite") == 0
    assert _train(small_scene, mine, *SMALL_RUN, "--overwrite") == 0
    assert (mine / "notes.txt").read_text() == "notes" and (mine / "metrics.json").is_file()
    assert not (mine / ".fastneus-previous").exists()


def _depth_wrong_shape(scene: Path, d: dict) -> None:
    np.save(scene / d["frames"][0]["gt"]["depth"], np.zeros((5, 7), np.float32))


def _gt_mesh_not_a_mesh(scene: Path, d: dict) -> None:
    (scene / "bad.ply").write_text("not a mesh")
    d["gt"] = {"mesh": "bad.ply"}


def _tiny_focal(scene: Path, d: dict) -> None:
    d["cameras"]["cam0"]["K"][0][0] = d["cameras"]["cam0"]["K"][1][1] = 1e-300


@pytest.mark.parametrize("mutate,extra,needle", [
    (_depth_wrong_shape, [], "frames[0].gt.depth"),
    (_gt_mesh_not_a_mesh, [], "gt.mesh"),
    (_tiny_focal, [], "cameras.cam0.K"),
    (None, ["bright_fraction=2"], "bright_fraction"),
    (None, ["mesh_resolution=1"], "mesh_resolution"),
])
def test_overwrite_checks_every_input_before_touching_the_run(run, small_scene, tmp_path, capsys, mutate, extra,
                                                              needle):
    scene = tmp_path / "scene"
    shutil.copytree(small_scene, scene)
    if mutate is not None:
        d = json.loads((scene / "scene.json").read_text())
        mutate(scene, d)
        (scene / "scene.json").write_text(json.dumps(d))
    before = _snapshot(run)
    assert _train(scene, run, *SMALL_RUN, *extra, "--overwrite") == 2
    _one_line_error(capsys, needle)
    assert _snapshot(run) == before  # not even a lock file is left


def test_overwrite_that_fails_before_its_first_checkpoint_restores_the_previous_run(run, small_scene, capsys,
                                                                                   monkeypatch):
    from fastneus.errors import FastneusError
    from fastneus.train.trainer import Trainer

    def boom(self, report=None):  # fails inside fit, after config.yaml and run.json were written
        raise FastneusError("kernel build failed (test)")

    before = _snapshot(run)
    monkeypatch.setattr(Trainer, "prime", boom)
    assert _train(small_scene, run, *SMALL_RUN, "--overwrite") == 2
    _one_line_error(capsys, "kernel build failed")
    assert _snapshot(run) == before


def test_a_killed_overwrite_gets_the_previous_run_back(run, small_scene, capsys):
    # what kill -9 after the move aside and before the first checkpoint leaves
    metrics = (run / "metrics.json").read_bytes()
    (run / ".fastneus-previous").mkdir()
    for n in ("checkpoint.pt", "metrics.json", "log.jsonl", "config.yaml", "mesh.ply", "renders"):
        os.replace(run / n, run / ".fastneus-previous" / n)
    (run / "config.yaml").write_text("partial: new run\n")
    assert _train(small_scene, run, *SMALL_RUN) == 2  # the previous run is back, so it is refused
    err = capsys.readouterr().err
    assert "restored the previous run" in err and "finished run" in err
    assert (run / "metrics.json").read_bytes() == metrics and (run / "checkpoint.pt").is_file()
    assert "partial" not in (run / "config.yaml").read_text() and not (run / ".fastneus-previous").exists()


# --------------------------------------------------------------------------- one writer (item 7)
def test_a_second_writer_is_refused_and_a_dead_ones_lock_taken_over(run, small_scene, capsys):
    from fastneus.train.runfolder import LOCK_NAME, run_lock

    with run_lock(run):  # another process training there (flock is per open file, so this counts)
        assert _train(small_scene, run, "--resume", "steps=6") == 2
        _one_line_error(capsys, str(run), "another fastneus process", f"pid {os.getpid()}")
        assert main(["eval", str(run), "--device", "cpu"]) == 2
        _one_line_error(capsys, "another fastneus process")
    (run / LOCK_NAME).write_text("999999999\n")  # left by a process that died: no lock is held
    assert _train(small_scene, run, "--resume", "steps=6") == 0


# --------------------------------------------------------------------------- torn log line (item 8) and temp files
def test_a_torn_last_log_line_is_dropped(run, small_scene, capsys):
    with open(run / "log.jsonl", "a") as f:
        f.write('{"step": 5, "time": 0.1, "lo')  # kill -9 mid-append
    capsys.readouterr()
    assert main(["eval", str(run), "--device", "cpu", "--resolution", "16"]) == 0
    assert "dropped 1 unreadable line" in capsys.readouterr().err
    assert _train(small_scene, run, "--resume", "steps=6") == 0
    assert "dropped a torn last line" in capsys.readouterr().err
    log = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]  # every line whole again
    assert log[-1]["step"] == 6


def test_stale_temp_files_of_killed_writes_are_removed(run, small_scene):
    (run / ".checkpoint.pt.k2j3h4.pt").write_bytes(b"x" * 1000)
    (run / ".metrics.json.abc.json").write_text("{")
    (run / "renders" / ".000_color.png.xyz.png").write_bytes(b"x")
    (run / ".my-notes").write_text("a user's hidden file")
    assert _train(small_scene, run, "--resume", "steps=5") == 0
    hidden = sorted(p.name for p in run.iterdir() if p.name.startswith("."))
    assert hidden == [".fastneus-run.json", ".my-notes"], hidden
    assert not [p for p in (run / "renders").iterdir() if p.name.startswith(".")]


# --------------------------------------------------------------------------- --resume's config (item 11)
def test_resume_continues_with_the_runs_own_config(run, small_scene, capsys):
    from fastneus.train.checkpoint import load_checkpoint

    # the run has log2_table=12 levels=4 (SMALL_RUN), which the preset does not: only steps given here
    assert _train(small_scene, run, "--resume", "steps=6", "lr=0.005") == 0
    st = load_checkpoint(run)
    c = st["config"]
    assert st["step"] == 6 and c["hashgrid"]["log2_table"] == 12 and c["hashgrid"]["levels"] == 4
    assert c["optim"]["lr"] == 0.005 and c["export"]["mesh_resolution"] == 16
    capsys.readouterr()
    before = _snapshot(run)
    assert _train(small_scene, run, "--resume", "steps=8", "levels=8") == 2
    _one_line_error(capsys, "levels", "cannot change")
    assert _train(small_scene, run, "--resume", "--config", "cpu-quick", "steps=8") == 2
    _one_line_error(capsys, "--config")
    assert _snapshot(run) == before
