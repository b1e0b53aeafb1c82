"""Every verb is discoverable from ``--help``: each verb has a description and each argument a
help line, and ``train --help`` names every scene format it reads (from the formats registry,
so a newly registered format shows up without touching the CLI)."""
from __future__ import annotations

import argparse
import contextlib
import io
from pathlib import Path

import pytest

from fastneus.cli import VERBS, build_parser, main


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


def _choice_help(parser: argparse.ArgumentParser) -> dict[str, str | None]:
    """The one-line help each verb has in ``fastneus --help``."""
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            return {c.dest: c.help for c in a._choices_actions}
    return {}


def undocumented(parser: argparse.ArgumentParser, path: str = "fastneus") -> list[str]:
    """What ``parser`` (and its sub-parsers, recursively) leaves without a description or help."""
    missing = []
    if not (parser.description or "").strip():
        missing.append(f"{path}: no description")
    for a in parser._actions:
        if isinstance(a, (argparse._HelpAction, argparse._VersionAction, argparse._SubParsersAction)):
            continue
        if a.help == argparse.SUPPRESS:
            continue
        if not (a.help or "").strip():
            missing.append(f"{path}: {'/'.join(a.option_strings) or a.dest}: no help")
    for name, sub in _subparsers(parser).items():
        missing += undocumented(sub, f"{path} {name}")
    return missing


def test_every_verb_is_in_the_parser():
    parser = build_parser()
    assert set(_subparsers(parser)) >= set(VERBS), set(VERBS) - set(_subparsers(parser))
    helps = _choice_help(parser)
    assert [v for v in VERBS if not (helps.get(v) or "").strip()] == [], "verbs without a line in fastneus --help"


def test_every_verb_and_argument_has_help():
    """Each verb has a description and each of its arguments a help line."""
    assert undocumented(build_parser()) == []


def test_the_walk_finds_what_is_missing():
    """The check itself can fail: a parser with a bare verb and a bare argument is reported."""
    p = argparse.ArgumentParser(prog="x", description="top")
    sub = p.add_subparsers()
    v = sub.add_parser("bare")
    v.add_argument("--flag")
    v.add_argument("pos", help="   ")
    assert undocumented(p) == ["fastneus bare: no description", "fastneus bare: --flag: no help",
                               "fastneus bare: pos: no help"]


def _help(verb: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        main([verb, "--help"])
    return " ".join(out.getvalue().split())  # argparse wraps lines: compare as one line


@pytest.mark.parametrize("verb", ["train", "oneshot", "convert"])
def test_scene_help_names_every_registered_format(verb):
    """``train --help`` lists the registry's formats, including one registered just now."""
    from fastneus.formats.registry import SceneFormat, formats, registered

    text = _help(verb)
    for f in formats():
        assert f.name in text, (f.name, text)
    toy = SceneFormat("toyfmt", "a toy 100% test format", lambda p: (Path(p) / "toy.json").is_file(),
                      reader="fastneus.data.scene:Scene.load")
    with registered(toy):
        text = _help(verb)
    assert "toyfmt" in text and "a toy 100% test format" in text
    assert "toyfmt" not in _help(verb)
