"""The nested config (one declaration per knob), the ``config`` verb and the public facade."""
from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
import yaml

from fastneus.cli import main
from fastneus.config import KEYS, SECTIONS, Config, config_from_dict, describe, load_config
from fastneus.errors import FastneusError


def test_every_knob_is_documented_and_listed(capsys):
    rows = describe()
    assert len(rows) == len(KEYS) > 80
    for key, default, rng, help_ in rows:
        sec, name = key.split(".")
        assert sec in SECTIONS and KEYS[name][0] == sec and help_.strip(), key
    assert main(["config"]) == 0
    out = capsys.readouterr().out
    for key, *_ in rows:  # the table folds long cells; every key's name is printed
        assert key.split(".")[1] in out, key


def test_config_verb_shows_a_preset_with_its_changes_marked(capsys):
    assert main(["config", "cpu-quick", "optim.lr=0.02"]) == 0
    out = capsys.readouterr().out
    data = yaml.safe_load(out)
    assert data["optim"]["lr"] == 0.02 and data["run"]["steps"] == 600
    line = next(x for x in out.splitlines() if x.strip().startswith("lr:"))
    assert "# default: 0.01" in line
    assert "# default" not in next(x for x in out.splitlines() if x.strip().startswith("lr_pose:"))


def test_config_is_frozen_and_replace_validates():
    cfg = Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.optim.lr = 1.0  # type: ignore[misc]
    assert cfg.replace(lr=0.5).optim.lr == 0.5 and cfg.optim.lr == 0.01
    with pytest.raises(FastneusError) as e:
        cfg.replace(lr=-1.0)
    assert e.value.field == "optim.lr"


@pytest.mark.parametrize("override", ["optim.lr=0.02", "lr=0.02"])
def test_dotted_and_bare_keys(override):
    assert load_config(None, [override]).optim.lr == 0.02


def test_a_key_in_the_wrong_section_is_refused():
    with pytest.raises(FastneusError) as e:
        load_config(None, ["rays.lr=0.02"])
    assert "optim.lr" in str(e.value) and "unknown" in str(e.value)


def test_saved_configs_round_trip_and_old_flat_ones_load(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("fastneus.config._NOTED", set())  # a note prints once per process: another test may have
    cfg = load_config("oneshot", ["steps=77"])
    again = config_from_dict(yaml.safe_load(yaml.safe_dump(cfg.to_dict())), "run/config.yaml")
    assert again == cfg
    # an earlier version's flat config.yaml, with a step-based schedule and a dropped key
    old = {"preset": "fewview", "steps": 1000, "lr": 0.003, "warmup_steps": 100, "render_frames": [0]}
    cfg = config_from_dict(old, "old/config.yaml")
    assert cfg.run.steps == 1000 and cfg.optim.lr == 0.003 and cfg.optim.warmup_frac == pytest.approx(0.1)
    assert "optim.warmup_frac" in capsys.readouterr().err


def test_presets_state_only_what_differs():
    from importlib import resources

    default = Config().to_dict()
    for res in resources.files("fastneus.configs").iterdir():
        if not res.name.endswith(".yaml"):
            continue
        data = yaml.safe_load(res.read_text()) or {}
        for sec, values in data.items():
            for k, v in values.items():
                if k != "preset":
                    assert v != default[sec][k], f"{res.name}: {sec}.{k} restates the default"


def test_facade_lists_its_names_and_loads_lazily():
    code = ("import sys, fastneus; print(sorted(fastneus.__all__)); "
            "print('torch' in sys.modules, 'fastneus.train' in sys.modules); "
            "fastneus.Config; print('fastneus.config' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()
    names = eval(out[0])  # noqa: S307 - our own printout
    for n in ("Config", "load_config", "Scene", "load_scene", "synthesize", "reconstruct", "Trainer",
              "extract_mesh", "evaluate"):
        assert n in names
    assert out[1] == "False False" and out[2] == "True"
    import fastneus

    for n in fastneus.__all__:
        assert getattr(fastneus, n) is not None


def test_facade_reconstructs_and_evaluates(small_scene, tmp_path):
    import fastneus

    from conftest import SMALL_RUN

    trainer, metrics = fastneus.reconstruct(small_scene, "cpu-quick", tmp_path / "run", "cpu",
                                            overrides=SMALL_RUN)
    assert (tmp_path / "run" / "mesh.ply").is_file() and "psnr_pattern" in metrics
    mesh = fastneus.extract_mesh(trainer, resolution=16)
    assert len(mesh.vertices) > 0
    again = fastneus.evaluate(tmp_path / "run", "cpu")
    assert again["psnr_pattern"] == pytest.approx(metrics["psnr_pattern"], abs=1e-3)
