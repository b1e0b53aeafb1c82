"""``loss.mask_thick``: the mask loss weakened away from the masks' thin parts (off by default)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import SMALL_RUN


def _disk_with_leg(w: int = 60, h: int = 40) -> np.ndarray:
    """[h, w] uint8 mask: a disk of radius 10 and a 2-px-wide leg running right from it."""
    yy, xx = np.mgrid[:h, :w]
    m = ((xx - 15) ** 2 + (yy - 20) ** 2 <= 100) | ((yy >= 19) & (yy <= 20) & (xx >= 15) & (xx <= 50))
    return (m * 255).astype(np.uint8)


def test_thin_parts_keep_the_full_weight_thick_ones_get_the_factor():
    from fastneus.train.rays import thin_part_weights, thin_part_width

    assert thin_part_width(128) == 5 and thin_part_width(200) == 5 and thin_part_width(400) == 9
    m = _disk_with_leg()
    blank = np.zeros((30, 20), np.uint8)  # a second frame of another size: no object, all factor
    flat = torch.from_numpy(np.concatenate([m.reshape(-1), blank.reshape(-1)]))
    w = thin_part_weights(flat, [(60, 40), (20, 30)], 0.3)
    assert w.dtype == torch.uint8 and w.shape == flat.shape
    a = w[:2400].reshape(40, 60).numpy()
    low = round(0.3 * 255)
    assert a[19, 35] == 255 and a[20, 45] == 255          # on the leg
    assert a[17, 35] == 255 and a[22, 45] == 255          # beside it (its outline and backdrop)
    assert a[20, 15] == low and a[12, 15] == low          # the disk's middle and its top outline
    assert a[5, 55] == low and a[38, 2] == low            # backdrop far from the leg
    assert (w[2400:] == low).all()
    # factor 1 everywhere full; a mask of thick parts only: no pixel kept at 255 with factor 0
    assert (thin_part_weights(flat, [(60, 40), (20, 30)], 1.0) == 255).all()
    for r in (12, 17.5):  # a digital disk's outline loses lone pixels to the opening: still no thin part
        disk = np.where(np.hypot(*np.mgrid[-20:20, -30:30]) <= r, 255, 0).astype(np.uint8)
        assert (thin_part_weights(torch.from_numpy(disk.reshape(-1)), [(60, 40)], 0.0) == 0).all()


def test_weighted_mask_bce_is_the_per_ray_weighted_mean():
    from fastneus.train import losses

    g = torch.Generator().manual_seed(0)
    op = torch.rand(64, generator=g) * 0.98 + 0.01
    m = (torch.rand(64, generator=g) > 0.5).float()
    pw = torch.rand(64, generator=g)
    got = losses.mask_bce(op, m, 0.7, pw)["mask"]
    want = 0.7 * (-(m * op.log() + (1 - m) * (1 - op).log()) * pw).mean()
    assert got.item() == pytest.approx(want.item(), rel=1e-5)
    assert losses.mask_bce(op, m, 0.7, torch.ones(64))["mask"].item() == pytest.approx(
        losses.mask_bce(op, m, 0.7)["mask"].item(), rel=1e-6)


@pytest.mark.parametrize("factor", [1.0, 0.3])
def test_a_run_carries_the_weights_and_says_so(small_scene, tmp_path, monkeypatch, factor):
    """Off (1): no weight map, no batch field, the note unchanged. On: the batch carries each ray's
    weight from the map, the choice is in the masks note (printed and saved in run.json), and a
    step trains."""
    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["camera_blur=0", "threads=1", f"mask_thick={factor}"])
    tr = Trainer(Scene.load(small_scene), cfg, tmp_path / "r", "cpu")
    assert tr.masks_used
    batch = tr.bank.sample(256, torch.Generator().manual_seed(1))
    if factor == 1.0:
        assert tr.bank.mask_w is None and "mask_w" not in batch and "mask_thick" not in tr.masks_note
        return
    assert "mask weight x0.3 away from thin parts" in tr.masks_note
    assert torch.equal(batch["mask_w"], tr.bank.mask_w[batch["pix"]].float() / 255.0)
    vals = batch["mask_w"].unique()
    assert all(min(abs(v - round(0.3 * 255) / 255.0), abs(v - 1.0)) < 1e-6 for v in vals.tolist())
    from fastneus.train import losses

    seen = []  # the per-ray weights that reach the mask term in a step

    def spy(opacity, mask, weight, pixel_weight=None):
        seen.append(pixel_weight)
        return bce(opacity, mask, weight, pixel_weight)

    bce = losses.mask_bce
    monkeypatch.setattr(losses, "mask_bce", spy)
    recs = [r for r in (tr.train_step() for _ in range(3)) if r is not None]
    assert recs and all(torch.isfinite(torch.as_tensor(r["loss"])).all() for r in recs)
    assert seen and all(w is not None and w.dim() == 1 and w.numel() > 0 for w in seen)
    assert any(bool((w < 1).any()) for w in seen)
