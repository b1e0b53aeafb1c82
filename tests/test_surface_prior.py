"""The decoded-surface prior (fastneus.train.geometry_init.SurfacePrior): its loss is ~0 for the SDF whose
zero set holds the points and grows as the surface moves off them; training keeps it (fading) after
a decoded / swept geometry init, and it holds the surface there against a misleading photo."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fastneus.config import load_config
from fastneus.errors import FastneusError
from fastneus.train.geometry_init import SurfacePrior


class _Sphere:
    """An analytic SDF |x| - r with the field's sdf / sdf_and_grad interface."""

    def __init__(self, r: float):
        self.r = torch.tensor(r, dtype=torch.float64, requires_grad=True)

    def sdf(self, x):
        return x.norm(dim=-1) - self.r

    def sdf_and_grad(self, x):
        return None, None, x / x.norm(dim=-1, keepdim=True), None


def _sphere_prior(r: float, n: int, gen: torch.Generator) -> SurfacePrior:
    # rays from cameras at distance 3 towards random points of the near side of a sphere of radius r
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1) * 3.0
    t = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    p = torch.nn.functional.normalize(-o + 0.5 * t * 3.0, dim=-1) * r  # a point on the sphere ...
    p = torch.where(((p - o) * p).sum(-1, keepdim=True) < 0, p, -p)  # ... on the side facing the camera
    d = torch.nn.functional.normalize(p - o, dim=-1)
    bo = o[: n // 4]
    u = torch.nn.functional.normalize(torch.cross(o[: n // 4], t[: n // 4], dim=-1), dim=-1)  # _|_ o
    bd = torch.nn.functional.normalize(-bo + 0.85 * u, dim=-1)  # passes ~0.82 from the centre: misses the object
    return SurfacePrior(p, d, o, bg_origins=bo, bg_dirs=bd)


def test_loss_is_zero_on_the_surface_and_grows_off_it():
    gen = torch.Generator().manual_seed(int(np.random.default_rng().integers(1 << 30)))
    r = 0.4 + 0.3 * float(torch.rand((), generator=gen))
    prior = _sphere_prior(r, 4000, gen)
    assert prior.nb == 1000  # they cross the unit sphere (rays that miss it are dropped)
    at = float(prior.loss(_Sphere(r), 4000, gen, eikonal=True).detach())
    assert at < 1e-6, at
    losses = [float(prior.loss(_Sphere(r + dr), 4000, torch.Generator().manual_seed(1), eikonal=False).detach())
              for dr in (0.005, 0.02, 0.08)]
    assert losses[0] > 1e-3 and losses[0] < losses[1] < losses[2], losses
    shrunk = float(prior.loss(_Sphere(r - 0.02), 4000, torch.Generator().manual_seed(1), eikonal=False).detach())
    assert shrunk > 0.01, shrunk
    # its gradient moves the surface back onto the points
    s = _Sphere(r + 0.03)
    prior.loss(s, 4000, gen, eikonal=False).backward()
    assert float(s.r.grad) > 0  # d loss / d r > 0: gradient descent shrinks r toward the points


def test_training_keeps_the_prior_after_a_decoded_init(tmp_path):
    """One Gray-code view: with the prior the SDF stays at the decoded points while training on
    photos whose pattern is wrong (illumination far off), without it it drifts further.

    Fixed scene seeds: over 8 random seeds the ratio was 0.29-0.55 on seven and 1.22 on one
    (seed 1, kept here on purpose), so a single random scene made CI flaky; the median of three
    fixed scenes is what is asserted."""
    from fastneus.train.geometry_init import decoded_points
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer

    ratios = []
    for seed in (0, 1, 2):
        s = synthesize(tmp_path / f"g{seed}", shape="toy", views=1, size=(48, 48), pattern="graycode",
                       seed=seed, progress=False, contact_sheet=False)
        dec = decoded_points(s, [list(range(20))])
        b = s.bounds
        P = torch.tensor((dec["points"] - b.center) / b.radius, dtype=torch.float32)
        drift = {}
        for w in (0.0, 1.0):
            cfg = load_config("cpu-quick", ["levels=8", "log2_table=14", "init_geometry_steps=60", "steps=20",
                                            "target_samples=16384", "occ_resolution=32",
                                            f"prior_weight={w}", "learn_illum=false", "log_every=1000",
                                            # the prior is under test, not the blur estimate (on a 20-pattern
                                            # sequence it blurs 20 full-size patterns per candidate: 13 s here)
                                            "save_every=100000", "camera_blur=0"])
            tr = Trainer(s, cfg, tmp_path / f"r{seed}_{w}", "cpu")
            tr.log_ir.data.fill_(np.log(4.0))  # a pattern 4x too bright pulls the surface off the code
            tr.fit(final_save=False)
            assert (tr.prior is None) == (w == 0)
            with torch.no_grad():
                drift[w] = float(tr.field.sdf(P).abs().mean())
        ratios.append(drift[1.0] / drift[0.0])
    assert float(np.median(ratios)) < 0.8, ratios  # seen: 0.55, 1.22, 0.29


def test_prior_weight_is_validated():
    with pytest.raises(FastneusError, match="prior_weight"):
        load_config("cpu-quick", ["prior_weight=-1"])
    with pytest.raises(FastneusError, match="prior_frac"):
        load_config("cpu-quick", ["prior_frac=0"])


def test_a_resumed_run_gets_the_prior_back_without_a_new_fit(tmp_path):
    from fastneus.train.geometry_init import initialise_geometry
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer, trainer_from_run

    s = synthesize(tmp_path / "g", shape="toy", views=1, size=(48, 48), pattern="graycode", seed=3, progress=False,
                   contact_sheet=False)
    cfg = load_config("cpu-quick", ["levels=8", "log2_table=14", "init_geometry_steps=20", "steps=6",
                                    "target_samples=16384", "occ_resolution=32", "log_every=1000"])
    tr = Trainer(s, cfg, tmp_path / "run", "cpu")
    tr.fit()
    assert tr.prior is not None
    again = trainer_from_run(s, tmp_path / "run", "cpu")
    assert again.step == 6 and again.prior is None
    before = [p.detach().clone() for p in again.field.parameters()]
    note = initialise_geometry(again)
    assert note is not None and "rebuilt on resume" in note
    assert again.prior is not None and len(again.prior) == len(tr.prior)
    assert all(torch.equal(a, b) for a, b in zip(before, again.field.parameters()))  # no second fit
    off = trainer_from_run(s, tmp_path / "run", "cpu", cfg=load_config("cpu-quick", [
        "levels=8", "log2_table=14", "steps=6", "prior_weight=0", "target_samples=16384", "occ_resolution=32"]))
    assert initialise_geometry(off) is None and off.prior is None
