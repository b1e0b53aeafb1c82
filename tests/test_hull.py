"""The masks' visual hull (fastneus.train.visibility.hull_cells) and what training does with it
(``occupancy.hull``: the SDF pushed positive outside it; ``bound``: the grid kept inside it)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from fastneus.config import load_config
from fastneus.synth.render import synthesize
from fastneus.train.rays import RayBank
from fastneus.train.visibility import consistent_hull, hull_cells, hull_uncovered, seen_cells

from conftest import SMALL_RUN


@pytest.fixture(scope="module")
def torus_scene(tmp_path_factory):
    """A torus (a hole through the middle, where the initial sphere sits) in 8 views with masks."""
    return synthesize(tmp_path_factory.mktemp("hull") / "t", shape="torus", views=8, size=(48, 48), illum="normal",
                      seed=3, progress=False, contact_sheet=False)


def _gt_points(scene, n: int = 20000) -> torch.Tensor:
    """GT surface samples in normalised space, [n, 3]."""
    m = trimesh.load(scene.path(scene.gt_mesh))
    p, _ = trimesh.sample.sample_surface(m, n, seed=int(np.random.default_rng().integers(1 << 30)))
    b = scene.bounds
    return torch.tensor((p - np.asarray(b.center)) / float(b.radius), dtype=torch.float32)


def _cell(p: torch.Tensor, r: int) -> torch.Tensor:
    ijk = ((p + 1.0) * (r / 2.0)).floor().long().clamp(0, r - 1)
    return ijk[:, 0] + ijk[:, 1] * r + ijk[:, 2] * r * r


def test_hull_holds_the_object_and_little_else(torus_scene):
    s, r = torus_scene, 32
    frames = list(range(len(s.frames)))
    for misses in (0, None):
        hull = hull_cells(s, frames, r, "cpu", misses=misses)
        assert hull.dtype == torch.bool and hull.shape == (r ** 3,)
        assert bool(hull[_cell(_gt_points(s), r)].all())  # conservative: every cell the surface crosses is in
    # tight: a small multiple of the torus's volume (8 views on one orbit), and far less than the seen space
    vol = trimesh.load(s.path(s.gt_mesh)).volume / float(s.bounds.radius) ** 3
    hull = hull_cells(s, frames, r, "cpu", misses=0)
    hull_vol = int(hull.sum()) * (2.0 / r) ** 3
    assert vol < hull_vol < 6.0 * vol
    assert int(hull.sum()) < 0.5 * int(seen_cells(s, frames, r, "cpu").sum())
    # the hole through the torus's middle is outside (the centre cell, seen from the orbit's views)
    assert not bool(hull[_cell(torch.zeros(1, 3), r)].any())


def test_hull_ignores_empty_masks_and_tolerates_a_bad_one(torus_scene, monkeypatch):
    s, r = torus_scene, 32
    frames = list(range(len(s.frames)))
    full = hull_cells(s, frames, r, "cpu", misses=0)
    real = type(s).mask

    def with_bad(kind):
        def mask(self, i):
            m = real(self, i)
            if i == 0 and kind == "empty":
                return np.zeros_like(m)
            if i == 0 and kind == "cut":  # half of the object missing from one mask
                m = m.copy()
                m[:, : m.shape[1] // 2] = 0.0
            return m
        return mask

    monkeypatch.setattr(type(s), "mask", with_bad("empty"))
    empty = hull_cells(s, frames, r, "cpu", misses=0)
    assert bool((empty | ~full).all()) and int(empty.sum()) >= int(full.sum())  # says nothing: no cell removed
    monkeypatch.setattr(type(s), "mask", with_bad("cut"))
    strict = hull_cells(s, frames, r, "cpu", misses=0)
    tolerant = hull_cells(s, frames, r, "cpu", misses=1)
    p = _cell(_gt_points(s), r)
    assert not bool(strict[p].all())  # one bad mask carves the object when no view may disagree ...
    assert bool(tolerant[p].all())  # ... and does not when one may
    monkeypatch.setattr(type(s), "mask", lambda self, i: None if i == 1 else real(self, i))
    assert hull_cells(s, frames, r, "cpu") is None  # a view without a mask: no hull


def test_consistent_hull_widens_for_a_calibration_that_is_off(torus_scene):
    """Poses off by a few degrees: the plain hull carves part of the torus, and leaves foreground
    pixels that no hull cell projects onto; the consistent hull widens until it covers them and
    then holds the whole surface. Exact poses: the plain hull, nothing uncovered."""
    from fastneus.synth.perturb import perturb_scene

    s, r = torus_scene, 32
    frames = list(range(len(s.frames)))
    hull, pad, worst = consistent_hull(s, frames, r, "cpu")
    assert pad == 0.0 and worst == 0.0 and torch.equal(hull, hull_cells(s, frames, r, "cpu"))
    assert max(hull_uncovered(s, frames, hull)) == 0.0
    off = perturb_scene(s, 4.0, 0.08, seed=1)
    p = _cell(_gt_points(off), r)
    plain = hull_cells(off, frames, r, "cpu")
    assert not bool(plain[p].all()) and max(hull_uncovered(off, frames, plain)) > 0.002
    wide, pad, worst = consistent_hull(off, frames, r, "cpu")
    assert pad > 0 and worst <= 0.002 and bool(wide[p].all())
    assert torch.equal(wide, hull_cells(off, frames, r, "cpu", extra_pad=pad))
    assert bool((wide | ~plain).all())  # wider: every plain-hull cell kept
    far = perturb_scene(s, 20.0, 0.4, seed=1)  # nothing consistent: no hull rather than a carved object
    none, pad, worst = consistent_hull(far, frames, r, "cpu")
    assert none is None and worst > 0.002


def test_trainer_widens_or_drops_the_hull_and_says_so(torus_scene, tmp_path):
    from fastneus.synth.perturb import perturb_scene

    s = torus_scene
    wide = _trainer(perturb_scene(s, 4.0, 0.08, seed=1), tmp_path / "w", [])
    assert wide.hull_out is not None and "widened by" in wide.hull_note
    far = _trainer(perturb_scene(s, 20.0, 0.4, seed=1), tmp_path / "f", [])
    assert far.hull_out is None and "disagree" in far.hull_note


def _trainer(scene, tmp_path, extra):
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["occ_resolution=32", "threads=1"] + extra)
    return Trainer(scene, cfg, tmp_path, "cpu")


@pytest.mark.parametrize("mode", ["loss", "bound"])
def test_hull_term_pushes_the_sdf_positive_outside_the_hull(torus_scene, tmp_path, mode):
    """The initial sphere fills the torus's hole: the hull term is positive there and its gradient
    raises the SDF at the uniform points outside the hull only; ``bound`` also narrows the grid."""
    s = torus_scene
    off = _trainer(s, tmp_path / "off", ["hull=off"])
    tr = _trainer(s, tmp_path / mode, [f"hull={mode}"])
    assert off.hull_out is None and "hull off" in off.hull_note
    auto = _trainer(s, tmp_path / "auto", [])  # the default: the term, not the bound
    assert auto.hull_out is not None and "hull auto -> loss" in auto.hull_note and torch.equal(auto.seen, off.seen)
    assert tr.hull_out is not None and "visual hull" in tr.hull_note
    if mode == "bound":
        assert int(tr.seen.sum()) < int(off.seen.sum()) and bool((tr.seen <= off.seen).all())
        assert int((tr.grid.allowed & (tr.hull_out > 0)).sum()) == 0  # never occupied outside the hull
    else:
        assert torch.equal(tr.seen, off.seen)
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    batch = tr.rig.rays(tr.bank.sample(64, gen))
    from fastneus.field.renderer import march_samples

    tr.grid.update(tr.field.sdf, 0.0, tr.cfg.rays.march_step, warmup=True)
    smp = march_samples(tr.grid.bits, tr.grid.resolution, batch["origins"], batch["dirs"], tr.cfg, jitter=False)
    xr = torch.rand(4000, 3, generator=gen) * 2 - 1
    loss, terms = tr.step_loss(batch, xr, smp, 0.5)
    with torch.no_grad():
        f = tr.field.sdf(xr).reshape(-1)
    r = tr.grid.resolution
    out = tr.hull_out[_cell(xr, r)]
    want = float(tr.cfg.occupancy.hull_weight * (out * torch.relu(-f)).mean())
    assert float(terms["hull"].detach()) == pytest.approx(want, rel=1e-4, abs=1e-7) and want > 0  # the sphere in the hole
    # the same points through shade_samples' extra-point path give the same SDF values
    from fastneus.field.renderer import shade_samples

    res = shade_samples(tr.field, smp, tr.rig.projection(), batch["origins"], batch["dirs"], batch["fidx"], tr.cfg,
                        i_r=torch.tensor(0.4), i_b=torch.tensor(0.1), cos_anneal=1.0, extra_points=xr)
    assert torch.allclose(res["sdf_extra"].detach(), f, atol=1e-5)
    # its gradient alone: a descent step raises f where the hull says empty and f < 0
    params = [tr.field.table] + list(tr.field.sdf_net.parameters())
    opt = torch.optim.SGD(params, lr=0.05)
    neg = (out > 0) & (f < 0)
    for _ in range(3):
        opt.zero_grad(set_to_none=True)
        (tr.cfg.occupancy.hull_weight * (out * torch.relu(-tr.field.sdf(xr).reshape(-1))).mean()).backward()
        opt.step()
    with torch.no_grad():
        f2 = tr.field.sdf(xr).reshape(-1)
    assert float(f2[neg].mean()) > float(f[neg].mean())
    assert float(loss.detach()) > float(terms["hull"].detach()) > 0


def test_hull_needs_masks(small_scene, tmp_path):
    from fastneus.data import Scene

    s = Scene.load(small_scene)
    tr = _trainer(s, tmp_path / "a", ["masks=off", "hull=loss"])
    assert tr.hull_out is None and "no masks" in tr.hull_note
    tr = _trainer(s, tmp_path / "b", ["hull=loss"])  # masks on: the term exists and a step runs
    assert tr.hull_out is not None
    for _ in range(2):
        tr.train_step()


def test_hull_margin_keeps_the_term_away_from_the_hull(torus_scene, tmp_path):
    """``hull_margin=m``: the term's space is the plain one less every cell within m cells of the
    hull (a thin part beside it shares the coarse hash levels with the pushed points)."""
    r = 32
    plain = _trainer(torus_scene, tmp_path / "p", ["hull=loss", "hull_margin=0"]).hull_out.bool()
    wide = _trainer(torus_scene, tmp_path / "w", ["hull=loss", "hull_margin=2"]).hull_out.bool()
    hull = hull_cells(torus_scene, list(range(len(torus_scene.frames))), r, "cpu")
    near = torch.nn.functional.max_pool3d(hull.reshape(1, 1, r, r, r).float(), 5, stride=1, padding=2).reshape(-1).bool()
    assert bool((wide & ~plain).sum() == 0) and int(wide.sum()) < int(plain.sum())
    assert not bool((wide & near).any()) and bool((plain & near).any())
    assert torch.equal(wide, plain & ~near)


def test_hull_cells_stay_occupied_for_hull_keep_frac(torus_scene, tmp_path):
    """``hull_keep=on``: a grid update before ``hull_keep_frac`` of the run leaves every cell of the
    masks' hull occupied, even where the field says empty (a thin part not formed yet); after it,
    the update alone decides; off keeps nothing, and auto only in a dark room (this torus is lit)."""
    r = 32
    tr = _trainer(torus_scene, tmp_path / "k", ["hull=loss", "hull_keep=on", "hull_keep_frac=0.5",
                                                "occ_warmup_frac=0.1"])
    off = _trainer(torus_scene, tmp_path / "o", ["hull=loss", "hull_keep=off"])
    auto = _trainer(torus_scene, tmp_path / "a", ["hull=loss", "hull_keep=auto"])
    assert off.hull_in is None and "hull_keep" not in off.hull_note
    assert not auto.dark_room and auto.hull_in is None
    assert tr.hull_in is not None and "stay occupied for the first 50% of the run" in tr.hull_note
    inside = tr.hull_in.bool()
    assert torch.equal(inside, (tr.hull_out == 0) & tr.seen)  # hull_margin=0: the term's space is the rest
    # a field that is empty everywhere (SDF 1): a plain update clears every cell
    with torch.no_grad():
        for t in (tr, off):
            t.field.sdf_net[-1].bias.fill_(1.0)
            t.field.sdf_net[-1].weight.zero_()
    for t in (tr, off):
        t.step = 0
        t._grid_open = False
    tr.update_grid(0.3)
    off.update_grid(0.3)
    assert int(off.grid.bits.sum()) == 0
    assert torch.equal(tr.grid.bits.bool(), inside) and int(inside.sum()) > 0
    tr.step = tr.cfg.occupancy.occ_update_every  # due again, now past the fraction
    tr.update_grid(0.6)
    assert int(tr.grid.bits.sum()) == 0
    assert r ** 3 == tr.grid.num_cells


def test_photo_masks_keep_the_object_and_drop_specks():
    """The photos' masks (no masks on disk): what the backdrop flags do not claim, less specks of
    noise, dilated by a pixel."""
    from types import SimpleNamespace

    from fastneus.train.rays import PHOTO_MASK_SPECK, photo_masks

    h, w = 20, 24
    bg = torch.ones(2, h, w, dtype=torch.bool)
    bg[0, 5:11, 6:9] = False          # an object, 18 px, with a 1-px leg
    bg[0, 11:16, 7] = False
    bg[0, 2, 20] = False              # a speck of noise
    bg[1, 0:2, 0:2] = False           # a 4-px blob: under the speck size
    bank = SimpleNamespace(bg=bg.reshape(-1), wh=torch.tensor([[w, h], [w, h]]), offset=torch.tensor([0, h * w]))
    out = photo_masks(bank, [3, 7])
    assert list(out) == [3, 7] and all(m.shape == (h, w) for m in out.values())
    m0, m1 = out[3], out[7]
    obj = ~bg[0].numpy()
    obj[2, 20] = False
    assert m0[obj].all() and not m0[2, 20] and m0[4, 5] and m0[16, 7] and not m0[0, 0]   # dilated by one
    assert int(m0.sum()) <= int(obj.sum()) * 5 and 4 < PHOTO_MASK_SPECK and not m1.any()
    assert photo_masks(SimpleNamespace(bg=None), [0]) is None


def test_a_dark_room_without_masks_gets_the_photos_hull(torus_scene, tmp_path, monkeypatch):
    """photo_hull=auto (cpu-quick): without masks, with the foreground prior on (a dark room), the
    hull is built from the photos; off, or with the prior off (a lit room), there is none."""
    import fastneus.train.trainer as trainer_mod

    s = torus_scene
    lit = _trainer(s, tmp_path / "lit", ["masks=off"])
    assert not lit.fg_used and lit.hull_out is None and "no masks, no hull" in lit.hull_note
    monkeypatch.setattr(trainer_mod, "DARK_ROOM", 0.0)  # every scene with a backdrop is a dark room now
    tr = _trainer(s, tmp_path / "dark", ["masks=off", "bg_prior=on"])
    assert tr.fg_used and tr.hull_out is not None, tr.hull_note
    assert "the photos' non-background pixels' visual hull" in tr.hull_note
    off = _trainer(s, tmp_path / "off", ["masks=off", "bg_prior=on", "photo_hull=off"])
    assert off.hull_out is None and "no masks, no hull" in off.hull_note
    # photo_hull=dark (fewview): not where the object is bright beside the backdrop (a lit room)
    for lit in (True, False):
        with monkeypatch.context() as m:
            m.setattr(RayBank, "lit_room", property(lambda self, lit=lit: lit))
            d = _trainer(s, tmp_path / f"d{lit}", ["masks=off", "bg_prior=on", "photo_hull=dark"])
        assert d.fg_used and (d.hull_out is None) == lit, d.hull_note
    # the photos' hull holds the object as the masks' does (sampled GT surface inside it)
    masked = _trainer(s, tmp_path / "m", [])
    r = tr.grid.resolution
    p = _gt_points(s, 4000)
    inside = (tr.hull_out == 0)[_cell(p, r)]
    assert float(inside.float().mean()) > 0.99 and masked.hull_out is not None
    for _ in range(2):
        tr.train_step()


def test_photo_masks_count_once_per_viewpoint(torus_scene):
    """Given masks go through the scene masks' rule: frames sharing a viewpoint count once (the first
    one's), an empty one says nothing, a missing one means no hull."""
    from fastneus.train.visibility import _hull_masks

    s = torus_scene
    frames = list(range(len(s.frames)))
    given = {i: s.mask(i) >= 0.5 for i in frames}
    assert [i for i, _ in _hull_masks(s, frames, given)] == [i for i, _ in _hull_masks(s, frames)]
    views = [s.frames[i].view for i in frames]
    assert len(_hull_masks(s, frames, given)) == len(set(views))
    given[frames[1]] = np.zeros_like(given[frames[1]])
    assert frames[1] not in [i for i, _ in _hull_masks(s, frames, given)]
    del given[frames[2]]
    assert _hull_masks(s, frames, given) is None
