"""Command-line entry point: ``fastneus <verb> ...``.

Each verb lives in its own module exposing ``register(subparsers)``; that function adds
the verb's parser and sets ``func`` to a handler taking the parsed args. Bad input
raises :class:`fastneus.errors.FastneusError`, printed here as one line (exit 2).
"""
from __future__ import annotations

from fastneus import timing as _timing

_timing.note_process_start()  # first thing: the wall clock of a run counts from here (or /proc's start)

import argparse  # noqa: E402
import importlib  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402

from fastneus.errors import FastneusError  # noqa: E402



def resolve_device(name: str | None) -> str:
    """Validate ``--device`` (cpu|cuda); default: cuda when available, else cpu."""
    import torch

    if name in (None, "", "auto"):
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name not in ("cpu", "cuda") and not name.startswith("cuda:"):
        raise FastneusError(f"unknown device {name!r}; use cpu or cuda", field="--device")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise FastneusError("CUDA was asked for but torch sees no CUDA GPU; use --device cpu", field="--device")
    return name


def add_device_arg(p: argparse.ArgumentParser) -> None:
    """Add the common ``--device cpu|cuda`` option (default: cuda when available)."""
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available, else cpu)")


def add_threads_arg(p: argparse.ArgumentParser) -> None:
    """Add the common ``--threads N`` option (the config key ``threads``; default: every CPU)."""
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="CPU threads for the kernels and torch (default: the FASTNEUS_THREADS environment "
                        "variable, else every CPU this process may use; same as threads=N)")


def threads_override(args) -> list[str]:
    """``["threads=N"]`` when ``--threads N`` was given (it wins over the config's key), else []."""
    n = getattr(args, "threads", None)
    if n is None:
        return []
    if n < 1:
        raise FastneusError(f"must be >= 1, got {n}", field="--threads")
    return [f"threads={n}"]


class _Parser(argparse.ArgumentParser):
    """argparse with the one-line error convention (usage stays in ``--help``)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# verb -> the module registering it (the parser of one verb is built without importing the
# others: ``fastneus train`` must not pay for synth's torch + trimesh + scipy imports)
VERBS = {
    "demo": "fastneus.cli.demo", "synth": "fastneus.cli.synth", "patterns": "fastneus.cli.patterns",
    "train": "fastneus.cli.train", "oneshot": "fastneus.cli.train", "batch": "fastneus.cli.batch",
    "mesh": "fastneus.cli.export", "render": "fastneus.cli.export", "eval": "fastneus.cli.export",
    "convert": "fastneus.cli.formats", "import-calib": "fastneus.cli.formats",
    "config": "fastneus.cli.config",
}
# verb modules, in the order shown by --help
VERB_MODULES = list(dict.fromkeys(VERBS.values()))


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``fastneus`` parser; with ``argv`` naming a known verb first, only that verb's module is imported."""
    parser = _Parser(
        prog="fastneus",
        description="Fast ActiveNeuS: reconstruct surfaces from images lit by calibrated projectors.",
    )
    from fastneus import __version__

    parser.add_argument("--version", action="version", version=f"fastneus {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="<verb>")
    first = argv[0] if argv else None
    names = [VERBS[first]] if first in VERBS else VERB_MODULES
    for name in names:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:  # a verb module not written yet must not break the others
            if e.name and (name == e.name or name.startswith(e.name + ".")):
                continue
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    # a real command line times its run from the process start; main(argv) inside another program from now
    _timing.begin_cli_run(from_process_start=argv is None)
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    # key=value overrides may come after options (argparse would leave them unparsed)
    args, extra = parser.parse_known_args(argv)
    if extra:
        if hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra):
            args.overrides = list(args.overrides or []) + extra
        else:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        rc = args.func(args)
        return int(rc or 0)
    except FastneusError as e:
        print(f"fastneus {args.verb}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # training turns Ctrl-C into one carrying where it saved
        print(f"fastneus {args.verb}: interrupted" + (f": {e}" if str(e) else ""), file=sys.stderr)
        return 130
    except BrokenPipeError:  # `fastneus config | head`: the reader left; not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as e:  # the environment (permissions, disk full, a file in the way), not a bug
        where = ": ".join(str(x) for x in (e.filename, e.filename2) if x)
        print(f"fastneus {args.verb}: error: {where + ': ' if where else ''}{e.strerror or e}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - last resort: one line unless debugging
        if os.environ.get("FASTNEUS_DEBUG"):
            raise
        print(f"fastneus {args.verb}: internal error: {type(e).__name__}: {e} "
              f"(set FASTNEUS_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
