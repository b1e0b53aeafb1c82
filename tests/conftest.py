"""Shared fixtures: one very small synthetic scene and run settings small enough for CPU tests."""
from __future__ import annotations

import pytest

# a model and batch small enough that building a trainer and a few steps take well under a second
SMALL_RUN = ["steps=4", "log_every=1", "save_every=2", "occ_resolution=16", "mesh_resolution=16", "log2_table=12",
             "levels=4", "finest_res=64", "target_samples=1024", "init_rays=64", "min_rays=32", "max_rays=128",
             "render_frames=[0]"]


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory):
    """A sphere in 3 views of 24x24 with masks and per-frame ground truth (fastneus format); do not modify.

    The GT mesh is left out of scene.json: Chamfer on 100k points would dominate these tests' time.
    """
    from fastneus.synth.render import synthesize

    out = tmp_path_factory.mktemp("small") / "sphere3"
    scene = synthesize(out, shape="sphere", views=3, size=(24, 24), pattern="crosslaser", illum="normal", seed=0,
                       device="cpu", proj_size=(64, 48), progress=False, contact_sheet=False)
    scene.gt_mesh = None
    scene.save()
    return out


def one_line_error(capsys, *needles: str) -> str:
    """The captured stderr: exactly one line, no traceback or "internal error", holding every needle."""
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "internal error" not in err, err
    for n in needles:
        assert n in err, (n, err)
    return err


def scene_on(small_scene, tmp_path, device: str):
    """The ``small_scene`` folder, or on CUDA the same scene rendered on the GPU into ``tmp_path``
    (a GPU machine may have no CPU compiler for Warp, so a CUDA test passes None for
    ``small_scene`` rather than requesting that CPU-built fixture)."""
    if device == "cpu":
        return small_scene
    path = tmp_path / "sphere3-cuda"
    if not (path / "scene.json").is_file():
        from fastneus.synth.render import synthesize

        synthesize(path, shape="sphere", views=3, size=(24, 24), pattern="crosslaser", illum="normal", seed=0,
                   device=device, proj_size=(64, 48), progress=False, contact_sheet=False)
    return path
