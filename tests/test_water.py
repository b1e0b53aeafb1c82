"""Underwater: flat-port refraction of camera rays (Snell) and its inverse for projections
(the Newton solve), ports in scene.json, the medium's image formation (synth = model), and
training with the model on and off."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fastneus.data import Scene
from fastneus.errors import FastneusError
from fastneus.kernels.project import port_dir_torch, port_row
from fastneus.geometry.projection import refract_rays


def test_refract_rays_obeys_snell_and_starts_on_the_outer_face():
    g = torch.Generator().manual_seed(0)
    row = torch.tensor(port_row([0.05, -0.1, 1.0], 0.03, 0.01, 1.0, 1.5, 1.333), dtype=torch.float64)
    n = row[:3]
    d = torch.nn.functional.normalize(torch.randn(100, 3, generator=g, dtype=torch.float64) * 0.4 +
                                      torch.tensor([0, 0, 1.0], dtype=torch.float64), dim=-1)
    d = d[(d @ n) > 0.3]  # toward the port (within ~70 deg of its normal)
    b, w = refract_rays(d, row)
    torch.testing.assert_close(b @ n, torch.full((d.shape[0],), 0.04, dtype=torch.float64))
    sin_a = torch.linalg.cross(d, n.expand_as(d)).norm(dim=-1)
    sin_w = torch.linalg.cross(w, n.expand_as(w)).norm(dim=-1)
    torch.testing.assert_close(1.333 * sin_w, 1.0 * sin_a)  # Snell air -> water (the glass cancels)
    # the camera model (refracted rays) and the projector model (Newton) are inverse maps
    X = b + 0.7 * w
    torch.testing.assert_close(port_dir_torch(X, row), d, atol=1e-10, rtol=0)


def _water_scene(tmp_path, medium="water", views=2, size=(32, 32)):
    from fastneus.synth.render import synthesize

    return synthesize(tmp_path / medium, shape="sphere", views=views, size=size, seed=0, device="cpu", progress=False,
                      contact_sheet=False, proj_size=(64, 48), noise=0.0, medium=medium)


def test_raybank_rays_project_back_to_their_pixels(tmp_path):
    from fastneus.train.rays import RayBank

    s = _water_scene(tmp_path)
    bank = RayBank(s, [1], "cpu")
    o, d, (h, w) = bank.image_rays(0)
    P = (o + 1.7 * d).double() * s.bounds.radius + torch.tensor(s.bounds.center)  # world, in the water
    X = P @ torch.tensor(s.world_to_cam(1)[:3, :3]).T + torch.tensor(s.world_to_cam(1)[:3, 3])
    V = port_dir_torch(X, torch.tensor(s.cameras["cam0"].port.row(), dtype=torch.float64))
    px = (V @ torch.tensor(s.cameras["cam0"].K).T)[:, :2] / V[:, 2:]
    v, u = np.mgrid[0:h, 0:w]
    torch.testing.assert_close(px, torch.tensor(np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)), atol=2e-3, rtol=0)
    o2, d2, _ = RayBank(s, [1], "cpu", refraction=False).image_rays(0)
    assert float((d2 - d).norm(dim=-1).max()) > 0.01  # refraction changes the rays


def test_ports_in_scene_json_round_trip_and_errors(tmp_path):
    s = _water_scene(tmp_path, views=1)
    d = json.loads((tmp_path / "water" / "scene.json").read_text())
    assert d["cameras"]["cam0"]["port"]["n_water"] == pytest.approx(1.333)
    assert d["projectors"]["proj0"]["port"]["thickness"] == pytest.approx(0.01)
    assert s.meta["medium"]["kind"] == "water"
    for edit, fld in [(lambda d: d["cameras"]["cam0"]["port"].__setitem__("normal", [0, 0, -1]), "cameras.cam0.port.normal"),
                      (lambda d: d["cameras"]["cam0"]["port"].__setitem__("distance", 0), "cameras.cam0.port.distance"),
                      (lambda d: d["projectors"]["proj1"]["port"].__setitem__("n_water", 0.9), "projectors.proj1.port.n_water")]:
        dd = json.loads(json.dumps(d))
        edit(dd)
        with pytest.raises(FastneusError) as e:
            Scene.from_dict(dd, tmp_path / "water")
        assert e.value.field == fld, str(e.value)


def test_medium_model_matches_synth_image_formation(tmp_path):
    """The trainer's water composite with the true coefficients reproduces synth's pixels: an
    opaque ray at range r and an empty ray (background)."""
    from fastneus.config import load_config
    from fastneus.train.rig import Rig
    from fastneus.train.rays import RayBank, build_projection
    from fastneus.synth.water import WATER, Water

    s = _water_scene(tmp_path, views=1)
    bank, proj = RayBank(s, [0], "cpu"), build_projection(s, [0], "cpu")
    rig = Rig(s, [0], bank, proj, load_config("cpu-quick").rig, "cpu")
    assert rig.medium_on and proj.port is not None
    with torch.no_grad():
        rig.log_beta_d.copy_(torch.tensor(WATER["beta_d"]).log())
        rig.log_beta_b.copy_(torch.tensor(WATER["beta_b"]).log())
        rig.b_inf_raw.copy_(torch.logit(torch.tensor(WATER["b_inf"])))
    r_world = torch.tensor([1.5, 3.0])
    c = torch.tensor([[0.5, 0.4, 0.3], [0.0, 0.0, 0.0]])
    out = {"opacity": torch.tensor([1.0, 0.0]), "depth": r_world / s.bounds.radius * torch.tensor([1.0, 0.0])}
    got = rig.composite(c, out, 0.0)
    water = Water(r_world[:1], torch.tensor([0]), 1, "cpu")
    torch.testing.assert_close(got[0], water.seen(c[:1])[0])
    torch.testing.assert_close(got[1], water.background()[0])
    off = Rig(s, [0], bank, proj, load_config("cpu-quick", ["medium=off"]).rig, "cpu")
    torch.testing.assert_close(off.composite(c, out, 0.0), c)


def test_synth_water_magnifies_and_colours_the_background(tmp_path):
    a = _water_scene(tmp_path, medium="air", views=1)
    w = _water_scene(tmp_path, medium="water", views=1)
    ma, mw = (a.mask(0) > 0.5).sum(), (w.mask(0) > 0.5).sum()
    assert 1.4 < mw / ma < 2.2  # a flat port magnifies by ~n_water / n_air per axis
    bg = w.image(0)[0, 0].astype(float) / 255
    assert np.allclose(bg, np.array([0.02, 0.12, 0.18]) * (1 - np.exp(-np.array([0.25, 0.12, 0.08]) * 20)), atol=2 / 255)
    with pytest.raises(FastneusError, match="medium"):
        from fastneus.synth.render import synthesize

        synthesize(tmp_path / "x", shape="sphere", views=1, size=(8, 8), progress=False, medium="oil")


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_training_in_water_model_on_and_off(tmp_path, backend):
    from fastneus.config import load_config
    from fastneus.train.trainer import Trainer

    s = _water_scene(tmp_path, views=2, size=(24, 24))
    steps = 6 if backend == "warp" else 2  # the torch twins are slow on CPU; they are compared op by op elsewhere
    over = [f"steps={steps}", "occ_resolution=16", "target_samples=2048", "init_rays=128", "max_rays=256",
            "log_every=1", "save_every=100", f"backend={backend}"]
    tr = Trainer(s, load_config("cpu-quick", over), tmp_path / "on", "cpu")
    assert tr.rig.medium_on and tr.proj.port is not None and tr.bank.port is not None
    before = [p.detach().clone() for p in (tr.rig.log_beta_d, tr.rig.log_beta_b, tr.rig.b_inf_raw)]
    tr.fit()
    assert tr.skipped == 0
    assert any(not torch.equal(a, b.detach()) for a, b in zip(before, (tr.rig.log_beta_d, tr.rig.log_beta_b,
                                                                       tr.rig.b_inf_raw)))
    assert "medium" in json.loads((tmp_path / "on" / "rig.json").read_text())
    if backend == "torch":
        return
    off = Trainer(s, load_config("cpu-quick", over + ["medium=off", "refraction=false"]), tmp_path / "off", "cpu")
    assert not off.rig.medium_on and off.proj.port is None and off.bank.port is None
    off.fit()
    assert off.skipped == 0


def test_activeneus_refraction_keys_round_trip(tmp_path):
    """Thin ports go to / come from the format's camera_refraction / projector_refraction."""
    import copy

    from fastneus.data.model import FlatPort
    from fastneus.formats.activeneus import read_activeneus, write_activeneus

    s = _water_scene(tmp_path, views=1, size=(16, 16))
    with pytest.raises(FastneusError, match="thin ports"):
        write_activeneus(s, tmp_path / "an0")  # 1 cm of glass has no form there
    t = copy.deepcopy(s)
    tilt = np.array([0.1, -0.05, 1.0]) / np.linalg.norm([0.1, -0.05, 1.0])
    t.cameras["cam0"].port = FlatPort(normal=tilt, distance=0.04, thickness=0.0, n_water=1.34)
    for k, p in enumerate(t.projectors.values()):
        p.port = FlatPort(normal=np.array([0, 0, 1.0]), distance=0.02 + 0.01 * k, n_water=1.33)
    write_activeneus(t, tmp_path / "an")
    d = np.load(tmp_path / "an" / "cameras_sphere.npz", allow_pickle=True)["camera_refraction"].item()
    assert d["normal"] == pytest.approx([0.1, -0.05]) and d["mu"] == pytest.approx(1.34)
    back = read_activeneus(tmp_path / "an")
    cp = back.cameras["cam0"].port
    assert np.allclose(cp.normal, tilt) and cp.distance == pytest.approx(0.04) and cp.n_water == pytest.approx(1.34)
    assert [p.port.distance for p in back.projectors.values()] == pytest.approx([0.02, 0.03, 0.04, 0.05])
    # the two descriptions refract a ray the same way
    from fastneus.kernels.project import port_row

    d0 = torch.tensor([[0.2, -0.1, 1.0]], dtype=torch.float64)
    d0 = d0 / d0.norm()
    a = refract_rays(d0, torch.tensor(t.cameras["cam0"].port.row(), dtype=torch.float64))
    b = refract_rays(d0, torch.tensor(port_row(cp.normal, cp.distance, 0.0, 1.0, cp.n_glass, cp.n_water),
                                      dtype=torch.float64))
    torch.testing.assert_close(a[0], b[0])
    torch.testing.assert_close(a[1], b[1])
