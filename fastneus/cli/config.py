"""Verb ``config``: every config key with its default, range and help; or a preset resolved."""
from __future__ import annotations

import sys


def _run(args) -> int:
    import yaml
    from rich.console import Console
    from rich.table import Table

    from fastneus.config import SECTIONS, Config, describe, load_config

    con = Console()
    if args.preset is None and not args.overrides and not sys.stdout.isatty():  # piped: one plain line per key
        for key, default, rng, help_ in describe():
            kind = ("one of " if "|" in rng else "in " if rng[:1] in "[(" else "") + rng if rng else ""
            print(f"{key} = {default}" + (f"  ({kind})" if kind else "") + f"  {help_}")
        return 0
    if args.preset is None and not args.overrides:
        table = Table(title="fastneus config keys (set with section.key=value, or key=value)", show_lines=False)
        for col in ("key", "default", "range", "what it does"):
            table.add_column(col, overflow="fold")
        last = None
        for key, default, rng, help_ in describe():
            sec = key.split(".", 1)[0]
            if last is not None and sec != last:
                table.add_section()
            last = sec
            table.add_row(key, default, rng, help_)
        con.print(table)
        con.print("presets: fastneus config PRESET shows one resolved (its keys that differ from the defaults marked)")
        return 0
    cfg = load_config(args.preset, list(args.overrides or []))
    default = Config().to_dict()
    lines = []
    for sec, values in cfg.to_dict().items():
        lines.append(f"{sec}:  # {SECTIONS[sec].__doc__.splitlines()[0]}")
        for k, v in values.items():
            text = yaml.safe_dump({k: v}, default_flow_style=True, width=10 ** 6).strip()[1:-1]
            mark = "" if v == default[sec][k] else f"  # default: {yaml.safe_dump(default[sec][k], default_flow_style=True).strip().removesuffix('...').strip()}"
            lines.append(f"  {text}{mark}")
    print("\n".join(lines))
    return 0


def register(sub) -> None:
    p = sub.add_parser("config", help="list every config key (default, range, help), or print a preset resolved",
                       description="Without arguments: every config key with its default, allowed range and "
                                   "help. With a preset name or YAML file (and key=value overrides): the "
                                   "resolved config as YAML, keys that differ from the defaults marked.")
    p.add_argument("preset", nargs="?", help="preset name (fewview, oneshot, cpu-quick, passive, paper) or YAML file")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. optim.lr=5e-3")
    p.set_defaults(func=_run)
