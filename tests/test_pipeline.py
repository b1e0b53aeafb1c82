"""End to end on a tiny synthetic scene: train, resume, checkpoints, mesh, eval, CLI errors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fastneus.cli import main
from fastneus.config import load_config

STEPS = 150
# tiny but real: a torus in 4 views of 40x40, cpu-quick-sized model
TINY = [f"steps={STEPS}", "log_every=10", "save_every=50", "mesh_resolution=48", "occ_resolution=32",
        "target_samples=8192", "init_rays=256", "max_rays=1024", "illum_warmup_frac=0.25",
        "render_frames=[0]", "c2f_frac=0.5"]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from fastneus.synth.render import synthesize

    # a torus, not a sphere: a sphere filling the bounds is explained by an all-solid field
    out = tmp_path_factory.mktemp("scene") / "torus4"
    synthesize(out, shape="torus", views=4, size=(40, 40), pattern="crosslaser", illum="normal", seed=0,
               device="cpu")
    return out


@pytest.fixture(scope="module")
def trained(tiny_scene, tmp_path_factory):
    from fastneus.formats.detect import load_scene
    from fastneus.pipeline import train_scene

    run = tmp_path_factory.mktemp("run") / "r"
    cfg = load_config("cpu-quick", TINY)
    trainer, metrics = train_scene(load_scene(tiny_scene), cfg, run, "cpu")
    return run, trainer, metrics


def test_loss_falls_mesh_inside_bounds_metrics_written(trained):
    run, trainer, metrics = trained
    log = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines()]
    assert len(log) >= 5
    first, last = np.mean([r["loss"] for r in log[:2]]), np.mean([r["loss"] for r in log[-2:]])
    assert last < 0.8 * first, (first, last)
    import trimesh

    mesh = trimesh.load(run / "mesh.ply", force="mesh")
    assert len(mesh.faces) > 50
    b = trainer.scene.bounds
    r = np.linalg.norm(mesh.vertices - np.asarray(b.center), axis=1)
    assert r.max() <= b.radius * 1.02
    m = json.loads((run / "metrics.json").read_text())
    for k in ("chamfer_gt2rec_mm", "chamfer_sym_mm", "fscore", "psnr_pattern", "psnr_texture", "i_r", "i_b"):
        assert k in m and np.isfinite(m[k]), k
    assert (run / "report.html").is_file() and (run / "illumination.json").is_file()
    assert m["steps"] == STEPS
    assert m["masks_used"] is True and m["fscore"] > 0.25, m  # the masks on disk were used; a torus was learned
    # visible-surface depth error on the 4 training viewpoints (mesh ray-cast vs GT depth)
    assert m["depth_views"] == 4 and 0 < m["depth_coverage"] <= 1 and np.isfinite(m["depth_err_pct"])


def test_resume_continues_step_count(trained, tiny_scene, tmp_path):
    from fastneus.formats.detect import load_scene
    from fastneus.pipeline import train_scene
    from fastneus.train.trainer import load_checkpoint

    run, _, _ = trained
    import shutil

    run2 = tmp_path / "resumed"
    shutil.copytree(run, run2)
    cfg = load_config("cpu-quick", TINY + [f"steps={STEPS + 20}"])
    tr, _ = train_scene(load_scene(tiny_scene), cfg, run2, "cpu", resume=True, finish=False)
    assert tr.step == STEPS + 20
    assert load_checkpoint(run2)["step"] == STEPS + 20
    log = [json.loads(x) for x in (run2 / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == STEPS + 20 and log[-1]["step"] > log[-3]["step"]


def test_interrupted_checkpoint_write_keeps_previous(trained, monkeypatch):
    from fastneus.train.trainer import load_checkpoint

    run, trainer, _ = trained
    before = load_checkpoint(run)["step"]

    def boom(obj, f, *a, **k):  # write half a file, then die as a crash would
        f.write(b"partial") if hasattr(f, "write") else Path(f).write_bytes(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", boom)
    trainer.step += 7
    with pytest.raises(KeyboardInterrupt):
        trainer.save()
    trainer.step -= 7
    monkeypatch.undo()
    assert load_checkpoint(run)["step"] == before
    assert not [p for p in run.iterdir() if p.name.startswith(".checkpoint")]


def test_texture_only_equals_zero_illumination(trained):
    from fastneus.field.renderer import render_rays

    run, tr, _ = trained
    batch = tr.bank.sample(256)
    kw = dict(cos_anneal=1.0, jitter=False)
    z = torch.zeros(1)
    with torch.no_grad():
        a = render_rays(tr.field, tr.grid.bits, tr.grid.resolution, tr.proj, batch["origins"], batch["dirs"],
                        batch["fidx"], tr.cfg, i_r=torch.tensor([0.7]), i_b=torch.tensor([0.3]), **kw)
        b = render_rays(tr.field, tr.grid.bits, tr.grid.resolution, tr.proj, batch["origins"], batch["dirs"],
                        batch["fidx"], tr.cfg, i_r=z, i_b=z, **kw)
    assert a["n_samples"] > 0
    torch.testing.assert_close(a["texture"], b["color"], rtol=1e-5, atol=1e-6)
    assert not torch.allclose(a["color"], a["texture"])  # the pattern does reach the surface


def test_cli_mesh_render_eval_on_run(trained, tmp_path, capsys):
    run, _, _ = trained
    assert main(["mesh", str(run), "--resolution", "40", "--out", str(tmp_path / "m.obj"), "--device", "cpu"]) == 0
    assert (tmp_path / "m.obj").stat().st_size > 0
    assert main(["render", str(run), "--frame", "1", "--out", str(tmp_path / "r"), "--device", "cpu"]) == 0
    assert (tmp_path / "r" / "001_texture.png").is_file()


@pytest.mark.parametrize("argv,needle", [
    (["train", "/no/such/scene"], "scene not found"),
    (["train", "{scene}", "no_such_key=1"], "no_such_key"),
    (["train", "{scene}", "steps=abc"], "steps"),
    (["train", "{scene}", "lr=-1"], "lr"),
    (["train", "{scene}", "--device", "tpu"], "--device"),
    (["train", "{scene}", "--config", "nope"], "preset"),
])
def test_bad_input_is_one_line(argv, needle, tiny_scene, capsys):
    argv = [a.replace("{scene}", str(tiny_scene)) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "Traceback" not in err and len(err.splitlines()) == 1, err


def test_nan_guard_skips_step_and_keeps_parameters():
    from fastneus.train.guard import finite_step

    p = torch.nn.Parameter(torch.randn(4))
    before = p.detach().clone()
    opt = torch.optim.Adam([p], lr=0.1)
    p.grad = torch.randn(4)
    p.grad[2] = float("nan")
    assert not finite_step(opt, torch.tensor(0.5))
    assert torch.equal(p.detach(), before) and p.grad is None
    p.grad = torch.randn(4)
    assert not finite_step(opt, torch.tensor(float("inf")))
    p.grad = torch.randn(4)
    assert finite_step(opt, torch.tensor(0.5))
    assert not torch.equal(p.detach(), before)
