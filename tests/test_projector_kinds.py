"""Projector kinds register in one place (fastneus/data/kinds.py, issue 21 item 4).

A toy kind registered from this file -- a "flood" projector lighting its whole frustum (z > 0
in its frame) with one colour -- reaches every place that handles projectors: scene.json
parse and save, packing for the light op, the renderer (a training step on CPU with the torch
backend) and synth lighting; it is gone again after the block.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fastneus.data.scene import Scene
from fastneus.data.validate import field_error
from fastneus.errors import FastneusError
from fastneus.data.kinds import (ProjectorKind, get_projector_kind, projector_kinds, register_projector_kind,
                                  registered)

CALLS = {"light": 0}


def parse_flood(entry: dict, file, fld: str) -> dict:
    col = entry.get("colour")
    if not (isinstance(col, list) and len(col) == 3
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) and 0 <= c <= 1 for c in col)):
        raise field_error("expected [r, g, b] in [0, 1]", file, f"{fld}.colour")
    return {"params": {"colour": [float(c) for c in col]}}


def flood_to_dict(p) -> dict:
    return {"colour": list(p.params["colour"])}


def pack_flood(projectors, device) -> torch.Tensor:
    return torch.tensor([[0.0, 0.0, 0.0] if p is None else p.params["colour"] for p in projectors],
                        dtype=torch.float32, device=device)


def flood_light(pos, ray_index, offsets, counts, ray_frame, proj_W, on, packed) -> torch.Tensor:
    """The light op (pure torch, differentiable): colour k wherever flood k is lit and X_z > 0."""
    CALLS["light"] += 1
    f = ray_frame.long()[ray_index.long()]
    q = torch.zeros(pos.shape[0], 3, dtype=pos.dtype, device=pos.device)
    for k in range(proj_W.shape[1]):
        Wk = proj_W[f, k].to(pos.dtype)
        z = (Wk[:, 2, :3] * pos).sum(-1) + Wk[:, 2, 3]
        lit = (on.long()[f, k] != 0) & (z > 0)
        q = q + lit[:, None].to(pos.dtype) * packed[k].to(pos.dtype)
    return q


def flood_synth(points, world_to_proj, projector) -> torch.Tensor:
    w2p = torch.as_tensor(np.asarray(world_to_proj), dtype=points.dtype, device=points.device)
    z = points @ w2p[2, :3] + w2p[2, 3]
    return (z > 0)[:, None].to(points.dtype) * torch.tensor(projector.params["colour"], dtype=points.dtype)


FLOOD = ProjectorKind("flood", "a flood light: one colour over its whole frustum (test toy)", parse_flood,
                      flood_to_dict, label="flood-light", pack=pack_flood, light=flood_light, synth=flood_synth)


def _flood_scene(root: Path) -> Path:
    from test_formats import make_scene

    make_scene(root, n=2, n_proj=1, seed=3)
    d = json.loads((root / "scene.json").read_text())
    d["projectors"]["F"] = {"kind": "flood", "proj_to_cam": np.eye(4).tolist(), "colour": [0.2, 0.4, 0.6]}
    d["frames"][0]["projectors"]["F"] = {"on": True}
    d["frames"][1]["projectors"]["F"] = {"on": False}
    (root / "scene.json").write_text(json.dumps(d))
    return root


def test_builtin_kinds_and_schema_agree():
    names = [k.name for k in projector_kinds()]
    assert names[:2] == ["pattern", "laser"] and get_projector_kind("pattern").images
    schema = json.loads((Path(__file__).resolve().parents[1] / "fastneus/data/scene.schema.json").read_text())
    assert schema["$defs"]["projector"]["properties"]["kind"]["enum"] == names
    with pytest.raises(ValueError):
        register_projector_kind(ProjectorKind("laser", "again", parse_flood, flood_to_dict, pack=pack_flood,
                                              light=flood_light))
    with pytest.raises(ValueError):  # an emitter needs its pack and light hooks
        register_projector_kind(ProjectorKind("half", "no light op", parse_flood, flood_to_dict))


def test_toy_kind_loads_saves_renders_and_synthesises(tmp_path):
    from fastneus.config import load_config
    from fastneus.train.rays import build_projection
    from fastneus.train.trainer import Trainer

    root = _flood_scene(tmp_path / "s")
    with pytest.raises(FastneusError) as e:  # not registered: an unknown kind, named with its field
        Scene.load(root)
    assert e.value.field == "projectors.F.kind"
    with registered(FLOOD):
        s = Scene.load(root)
        pj = s.projectors["F"]
        assert pj.kind == "flood" and pj.params == {"colour": [0.2, 0.4, 0.6]} and pj.K.shape == (3, 3)
        assert s.active_projectors(0) == [("p0", "q0")]  # a flood shows no pattern

        # save -> load round trip
        s.save(tmp_path / "s2")
        d2 = json.loads((tmp_path / "s2" / "scene.json").read_text())
        assert d2["projectors"]["F"]["kind"] == "flood" and d2["projectors"]["F"]["colour"] == [0.2, 0.4, 0.6]
        assert d2["frames"][1]["projectors"]["F"] == {"on": False}
        assert Scene.load(tmp_path / "s2").projectors["F"].params == pj.params

        # one-line errors naming file and field
        d = json.loads((root / "scene.json").read_text())
        for edit, fld in [(lambda d: d["projectors"]["F"].__setitem__("colour", [2, 0, 0]), "projectors.F.colour"),
                          (lambda d: d["frames"][0]["projectors"]["F"].__setitem__("pattern", "q0"),
                           "frames[0].projectors.F.pattern")]:
            dd = json.loads(json.dumps(d))
            edit(dd)
            with pytest.raises(FastneusError) as e:
                Scene.from_dict(dd, root)
            assert e.value.field == fld and "\n" not in str(e.value) and "scene.json" in str(e.value)
        with pytest.raises(FastneusError, match="flood-light projectors"):
            from fastneus.formats.nerf import write_nerf

            write_nerf(s, tmp_path / "nerf")

        # packed for the light op: on where lit, colours per projector (zeros for the pattern projector)
        pr = build_projection(s, [0, 1], "cpu")
        on, packed = pr.lights["flood"]
        assert on.tolist() == [[0, 1], [0, 0]] and packed.tolist()[1] == pytest.approx([0.2, 0.4, 0.6])
        assert pr.laser_on is None and int(pr.pattern[0, 0]) == 0

        # a training step on CPU (torch backend) lights the rays of frame 0 through flood_light
        over = ["occ_resolution=16", "target_samples=512", "init_rays=64", "min_rays=64", "max_rays=64", "log_every=1",
                "save_every=100", "backend=torch", "steps=1"]
        CALLS["light"] = 0
        tr = Trainer(s, load_config("cpu-quick", over), tmp_path / "run", "cpu")
        tr.fit()
        assert tr.step == 1 and tr.skipped == 0 and CALLS["light"] > 0

        # synth lighting: the kind's hook, dispatched as synthesize does
        pts = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
        q = get_projector_kind(pj.kind).call("synth", pts, np.eye(4), pj)
        assert q.tolist() == [pytest.approx([0.2, 0.4, 0.6]), [0.0, 0.0, 0.0]]
    assert "flood" not in [k.name for k in projector_kinds()]
    with pytest.raises(FastneusError):
        Scene.load(root)
