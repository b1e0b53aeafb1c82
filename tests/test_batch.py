"""``fastneus batch`` on CPU: three tiny scenes (one broken) -> two meshes and one recorded error; a
re-run skips the finished runs; Ctrl-C is forwarded so a run saves and the next batch resumes it;
the Ray path on a small local cluster; run folder names; one-line errors for bad input."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import SMALL_RUN, one_line_error

from fastneus.batch.local import plan_workers
from fastneus.batch.plan import SUMMARY, expand_scenes, plan, safe_name
from fastneus.cli import main

ARGS = ["--threads", "1", *SMALL_RUN]


@pytest.fixture(scope="module")
def scans(small_scene, tmp_path_factory):
    """Two copies of the small sphere (same folder name), one broken copy, and a list naming all three."""
    root = tmp_path_factory.mktemp("scans")
    for d in ("a", "b"):
        shutil.copytree(small_scene, root / d / "sphere")
    broken = root / "c" / "broken scan"
    shutil.copytree(small_scene, broken)
    d = json.loads((broken / "scene.json").read_text())
    d["cameras"][next(iter(d["cameras"]))]["width"] = -5
    (broken / "scene.json").write_text(json.dumps(d))
    (root / "scans.txt").write_text("# three scans\na/sphere\nb/sphere   # same name as a's\n\nc/*\n")
    return root


def _files(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


def _summary(out: Path) -> dict:
    return json.loads((out / SUMMARY).read_text())


def _states(out: Path) -> dict[str, str]:
    return {s["name"]: s["state"] for s in _summary(out)["scenes"]}


@pytest.fixture(scope="module")
def batch(scans, tmp_path_factory):
    """The first batch of the list, and what the scans folder held before."""
    before = _files(scans)
    out = tmp_path_factory.mktemp("batch") / "out"
    rc = main(["batch", str(scans / "scans.txt"), "--out", str(out), "--workers", "2", *ARGS])
    return out, rc, before


def test_batch_two_meshes_one_recorded_error(batch, scans):
    out, rc, before = batch
    assert rc == 1  # a scene failed
    s = _summary(out)
    assert _states(out) == {"sphere": "done", "sphere-2": "done", "broken_scan": "failed"}, s
    assert s["counts"]["done"] == 2 and s["counts"]["failed"] == 1
    by = {r["name"]: r for r in s["scenes"]}
    assert by["sphere"]["scene"] == str(scans / "a" / "sphere") and by["sphere-2"]["scene"] == str(scans / "b" / "sphere")
    for name in ("sphere", "sphere-2"):
        assert (out / name / "mesh.ply").is_file() and (out / name / "metrics.json").is_file()
        assert by[name]["error"] is None and by[name]["steps"] == 4
    err = by["broken_scan"]["error"]
    assert "scene.json" in err and "cameras." in err and "width" in err and len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    assert _files(scans) == before  # nothing written next to the scenes
    assert s["workers"] == ["cpu 0", "cpu 1"] and s["threads_per_run"] == 1


def test_rerun_skips_finished_runs(batch, scans, capsys):
    out, _, _ = batch
    meshes = {n: (out / n / "mesh.ply").stat().st_mtime_ns for n in ("sphere", "sphere-2")}
    capsys.readouterr()
    rc = main(["batch", str(scans / "scans.txt"), "--out", str(out), "--workers", "2", *ARGS])
    text = capsys.readouterr().out
    assert rc == 1
    assert _states(out) == {"sphere": "skipped", "sphere-2": "skipped", "broken_scan": "failed"}
    assert {n: (out / n / "mesh.ply").stat().st_mtime_ns for n in meshes} == meshes  # not trained again
    assert "2 finished before (skipped)" in text and "broken_scan: failed" in text  # plain lines: not a TTY
    assert sorted(p.name for p in out.iterdir()) == ["broken_scan", "sphere", "sphere-2", SUMMARY]


def test_ctrl_c_is_forwarded_and_the_next_batch_resumes(small_scene, tmp_path):
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "fastneus", "batch", str(small_scene), "--out", str(out), *ARGS, "steps=100000"]
    with open(tmp_path / "batch.txt", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    try:
        steps = out / "sphere3" / "log.jsonl"
        deadline = time.monotonic() + 240  # a guard against a hang, not a timing check
        while not (steps.is_file() and len(steps.read_text().splitlines()) >= 3) and proc.poll() is None:
            assert time.monotonic() < deadline, (tmp_path / "batch.txt").read_text()
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = (tmp_path / "batch.txt").read_text()
    assert rc == 130, text
    rec = _summary(out)["scenes"][0]
    assert rec["state"] == "interrupted" and "checkpoint saved" in rec["error"], rec
    assert (out / "sphere3" / "checkpoint.pt").is_file() and not (out / "sphere3" / "metrics.json").exists()
    stopped_at = json.loads((out / "sphere3" / "log.jsonl").read_text().splitlines()[-1])["step"]
    assert 3 <= stopped_at < 100000
    # the same batch (a shorter run asked for): resumed from the checkpoint, not refused nor restarted
    rc = main(["batch", str(small_scene), "--out", str(out), *ARGS])
    rec = _summary(out)["scenes"][0]
    assert rc == 0 and rec["state"] == "done", rec
    assert rec["steps"] >= stopped_at and (out / "sphere3" / "mesh.ply").is_file()


def test_ray_batch_on_a_local_cluster(scans, tmp_path):
    ray = pytest.importorskip("ray", reason='Ray is not installed (pip install "fastneus[ray]")')
    out = tmp_path / "out"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        rc = main(["batch", str(scans / "a" / "sphere"), str(scans / "c" / "*"), "--out", str(out), "--ray", "auto",
                   *ARGS])
    finally:
        ray.shutdown()
    s = _summary(out)
    assert rc == 1 and s["scheduler"] == "ray"
    assert _states(out) == {"sphere": "done", "broken_scan": "failed"}, s
    assert (out / "sphere" / "mesh.ply").is_file()
    assert "cameras." in s["scenes"][1]["error"] and s["scenes"][0]["worker"].startswith("ray")
    assert s["ray_resources"] == {"num_cpus": 1}


# --------------------------------------------------------------------------- planning (no training)
@pytest.mark.parametrize("folder, name", [("scan 01", "scan_01"), ("..hidden", "hidden"), ("é", "scene"),
                                          ("a..b", "a.b"), ("x" * 80, "x" * 56), ("-_.", "scene")])
def test_run_names_are_safe(folder, name):
    assert safe_name(Path("/data") / folder) == name
    assert safe_name(Path("/data") / folder / "scene.json") == name  # a scene's main file: its folder names it


def test_names_are_unique_stable_and_never_a_link(tmp_path):
    scenes = [tmp_path / "a" / "s", tmp_path / "b" / "s", tmp_path / "c" / "summary.json" / "..", tmp_path / "d" / "s"]
    out = tmp_path / "out"
    (out / "s-2").mkdir(parents=True)
    (out / "s-2" / ".fastneus-batch.json").write_text(json.dumps({"scene": str(tmp_path / "b" / "s")}))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / "s").symlink_to(elsewhere)  # never written through: a/s gets another name
    names = [j.name for j in plan(scenes, out)]
    assert names[1] == "s-2"  # b/s keeps the folder it had
    assert names[0] not in ("s", "s-2") and len(set(names)) == 4 and "summary.json" not in names
    assert all(n == safe_name(Path(n)) for n in names)


def test_scenes_from_globs_and_lists(scans):
    got = expand_scenes([str(scans / "scans.txt"), str(scans / "a" / "sphere")])
    assert got == [scans / "a" / "sphere", scans / "b" / "sphere", scans / "c" / "broken scan"]


def test_workers_per_gpu_and_per_cores(monkeypatch):
    pool, threads, note = plan_workers("0,1", None, None, None)
    assert [w.env for w in pool] == [{"CUDA_VISIBLE_DEVICES": "0"}, {"CUDA_VISIBLE_DEVICES": "1"}] and "2 GPU" in note
    monkeypatch.setattr("fastneus.batch.local.available_cores", lambda: 8)
    pool, threads, note = plan_workers(None, None, "cpu", None)
    assert len(pool) == 2 and threads == 4 and "8 CPU core" in note
    pool, threads, _ = plan_workers(None, None, "cpu", 1)
    assert len(pool) == 8 and threads == 1


@pytest.mark.parametrize("extra, needles", [
    (["nosuchkey=1"], ["nosuchkey"]),
    (["--gpus", "0,0"], ["--gpus"]),
    (["--device", "cpu", "--gpus", "0"], ["--gpus"]),
    (["--workers", "0"], ["--workers"]),
])
def test_bad_options_one_line_nothing_written(small_scene, tmp_path, capsys, extra, needles):
    out = tmp_path / "out"
    assert main(["batch", str(small_scene), "--out", str(out), *extra]) == 2
    one_line_error(capsys, "fastneus batch: error:", *needles)
    assert not out.exists() or not any(out.iterdir())


def test_glob_without_match_and_ray_without_the_extra(tmp_path, capsys, monkeypatch, small_scene):
    assert main(["batch", str(tmp_path / "none-*"), "--out", str(tmp_path / "o")]) == 2
    one_line_error(capsys, "matches no scene folder")
    monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed
    assert main(["batch", str(small_scene), "--out", str(tmp_path / "o"), "--ray", "auto"]) == 2
    one_line_error(capsys, "--ray", 'pip install "fastneus[ray]"')
    assert not (tmp_path / "o").exists()
