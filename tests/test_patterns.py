"""Pattern generators: shapes, dtypes, determinism, Gray-code / phase-shift decoding, CLI."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from fastneus.cli import main
from fastneus.errors import FastneusError
from fastneus.light.patterns import KINDS, decode_graycode, decode_phaseshift, make_pattern


@pytest.mark.parametrize("kind", KINDS)
def test_shapes_and_determinism(kind):
    a = make_pattern(kind, 64, 48, seed=3)
    b = make_pattern(kind, 64, 48, seed=3)
    assert isinstance(a, list) and len(a) >= 1
    for im, jm in zip(a, b):
        assert im.dtype == np.uint8 and im.shape == (48, 64, 3)
        np.testing.assert_array_equal(im, jm)
    assert any(im.max() > 0 for im in a)


@pytest.mark.parametrize("kind", ["crosslaser", "colorline", "dots", "grid"])
def test_seed_changes_random_patterns(kind):
    a = make_pattern(kind, 64, 48, seed=1)[0]
    b = make_pattern(kind, 64, 48, seed=2)[0]
    assert not np.array_equal(a, b)


def test_crosslaser_colours():
    im = make_pattern("crosslaser", 1024, 768, count=4, line_width=3)[0]
    cols = {tuple(c) for c in np.unique(im.reshape(-1, 3), axis=0)}
    assert cols == {(0, 0, 0), (255, 0, 0), (0, 255, 0), (255, 255, 0)}
    red_cols = np.where((im[..., 0] == 255).all(axis=0))[0]  # vertical red lines span all rows
    assert len(red_cols) == 4 * 3
    green_rows = np.where((im[..., 1] == 255).all(axis=1))[0]
    assert len(green_rows) == 4 * 3


def test_colorline_like_sample():
    im = make_pattern("colorline", 1024, 768, seed=0)[0]
    assert (im == im[:1]).all()  # vertical stripes
    assert {tuple(c) for c in np.unique(im.reshape(-1, 3), axis=0)} <= {
        (r, g, b) for r in (0, 255) for g in (0, 255) for b in (0, 255)}
    row = im[0].astype(int)
    change = np.any(row[1:] != row[:-1], axis=1).nonzero()[0]
    assert np.all(np.diff(change) == 4)


@pytest.mark.parametrize("inverse", [False, True])
@pytest.mark.parametrize("size", [(1024, 768), (100, 37)])
def test_graycode_decodes(size, inverse):
    w, h = size
    ims = make_pattern("graycode", w, h, inverse=inverse)
    assert len(ims) == (int(np.ceil(np.log2(w))) + int(np.ceil(np.log2(h)))) * (2 if inverse else 1)
    col, row = decode_graycode(ims, w, h, inverse=inverse)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    np.testing.assert_array_equal(col, jj)
    np.testing.assert_array_equal(row, ii)
    with pytest.raises(FastneusError):
        decode_graycode(ims[:-1], w, h, inverse=inverse)


def test_phaseshift_decodes():
    ims = make_pattern("phaseshift", 64, 8, count=4, period=16)
    phase = decode_phaseshift(ims)[0]
    expect = np.mod(2 * np.pi * (np.arange(64) + 0.5) / 16, 2 * np.pi)
    err = np.angle(np.exp(1j * (phase - expect)))
    assert np.abs(err).max() < 0.05


def test_unknown_kind():
    with pytest.raises(FastneusError, match="--kind"):
        make_pattern("laser", 10, 10)


def test_cli(tmp_path, capsys):
    rc = main(["patterns", "--kind", "graycode", "--size", "64x32", "--out", str(tmp_path), "--inverse"])
    assert rc == 0
    files = sorted(tmp_path.glob("graycode_*.png"))
    assert len(files) == (6 + 5) * 2
    im = cv2.imread(str(files[0]))
    assert im.shape == (32, 64, 3)
    assert "wrote 22 graycode patterns" in capsys.readouterr().out
    assert main(["patterns", "--kind", "grid", "--size", "64by32", "--out", str(tmp_path)]) == 2


def test_a_pattern_kind_registered_from_outside_reaches_every_verb(tmp_path):
    """One register_pattern_kind call: make_pattern, `fastneus patterns` and `fastneus synth` take it."""
    import numpy as np

    from fastneus.cli import main
    from fastneus.light.patterns import PatternKind, register_pattern_kind, unregister_pattern_kind
    from fastneus.synth.render import synthesize

    def checker(width, height, seed=0, **opts):
        y, x = np.mgrid[:height, :width]
        on = ((x // 8 + y // 8) % 2).astype(np.uint8) * 255
        return [np.stack([on, on, on], -1)]

    register_pattern_kind(PatternKind("checker", checker, help="a toy checkerboard"))
    try:
        assert make_pattern("checker", 32, 16)[0].shape == (16, 32, 3)
        assert main(["patterns", "--kind", "checker", "--size", "32x16", "--out", str(tmp_path / "p")]) == 0
        assert (tmp_path / "p" / "checker_00.png").is_file()
        scene = synthesize(tmp_path / "s", shape="sphere", views=2, size=(24, 24), pattern="checker",
                           proj_size=(64, 48), contact_sheet=False, progress=False)
        assert len(scene.frames) == 2 and len(scene.patterns) >= 1
    finally:
        unregister_pattern_kind("checker")
    assert "checker" not in KINDS
    with pytest.raises(Exception, match="unknown pattern kind"):
        make_pattern("checker", 8, 8)
