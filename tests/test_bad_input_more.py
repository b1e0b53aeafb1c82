"""More bad input (issue 20 items 5, 6, 9, 10): inputs that hung, ended as an "internal error",
or were accepted and silently trained something wrong.

One table of crafted inputs (built from the corpus's valid bases in ``tests/test_bad_input_corpus.py``)
run through the CLI in-process: each must exit 2 with exactly one line on stderr naming the file
and/or field at fault, and leave the output folder as it was. A few behaviours that are not a
refusal (EXIF orientation, JSON without NaN, a full disk) have their own tests below.
"""
from __future__ import annotations

import errno
import json
import shutil
import struct
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
import torch

from fastneus.cli import main
from test_bad_input_corpus import Ctx, _calib, _colmap, _snapshot, bases  # noqa: F401 - bases is a fixture

CASES: dict[str, Callable] = {}


def case(name: str):
    def reg(fn):
        assert name not in CASES
        CASES[name] = fn
        return fn
    return reg


def _yaml(c, text: str, name: str = "my.yaml") -> str:
    p = c.tmp / name
    p.write_text(text)
    return str(p)


def _ckpt(c, edit: Callable[[dict], None]) -> Path:
    """A copy of the base run whose checkpoint is edited by ``edit``."""
    run = c.run()
    st = torch.load(run / "checkpoint.pt", weights_only=True)
    edit(st)
    torch.save(st, run / "checkpoint.pt")
    return run


# --------------------------------------------------------------------------- item 5: unpickler work bound
@case("an-illumination-shared-references")
def _(c):
    leaf = [1.0]
    for _ in range(6):  # ~1 KB of pickle, 64^6 leaves when walked naively
        leaf = [leaf] * 64
    ip = np.array({"ambient": leaf, "diffuse": 0.4, "emissive": 0.1}, dtype=object)
    return c.train(c.npz("an", illumination_params=ip)) + (["cameras_sphere.npz", "illumination_params", "refused"],)


# --------------------------------------------------------------------------- the runner
@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input(name, bases, tmp_path, capsys):  # noqa: F811 - bases is the imported fixture
    c = Ctx(bases, tmp_path)
    argv, guard, needles = CASES[name](c)
    before = _snapshot(guard)
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    err = capsys.readouterr().err.strip()
    assert rc == 2, f"{name}: exit {rc}:\n{err}"
    assert len(err.splitlines()) == 1, f"{name}: not one line:\n{err}"
    assert "Traceback" not in err and "internal error" not in err, err
    for n in needles:
        assert n in err, f"{name}: {n!r} not named in: {err}"
    assert _snapshot(guard) == before, f"{name}: the earlier result in {guard} changed"
    assert not [p for p in tmp_path.rglob(".*staging-*")], "staging folder left behind"
