"""Small helpers shared by the benchmark scripts: timing, machine info, Markdown sections."""
from __future__ import annotations

import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_fn(fn, device: str, warmup: int = 3, repeat: int = 20) -> float:
    """Median wall time of ``fn()`` in milliseconds (device-synchronised)."""
    for _ in range(warmup):
        fn()
    sync(device)
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        sync(device)
        ts.append((time.perf_counter() - t) * 1000)
    return statistics.median(ts)


def machine(device: str) -> str:
    """One line naming the machine (GPU model or CPU model and core count)."""
    if device.startswith("cuda") and torch.cuda.is_available():
        return f"{torch.cuda.get_device_name()} (torch {torch.__version__})"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores (torch {torch.__version__})"


def git_rev() -> str:
    try:
        return subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True).strip()
    except Exception:  # noqa: BLE001
        return "unknown"


def md_table(rows: list[dict], cols: list[str]) -> str:
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:,.0f}"
        return str(v)
    head = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"
    return head + "".join("| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |\n" for r in rows)


def update_section(md: Path, key: str, text: str, title: str = "# Benchmarks\n") -> None:
    """Replace (or append) the block between ``<!-- key -->`` and ``<!-- /key -->`` in ``md``."""
    from fastneus.io import atomic_write_text

    body = md.read_text() if md.is_file() else title
    block = f"<!-- {key} -->\n{text.rstrip()}\n<!-- /{key} -->"
    pat = re.compile(rf"<!-- {re.escape(key)} -->.*?<!-- /{re.escape(key)} -->", re.S)
    body = pat.sub(lambda _: block, body) if pat.search(body) else body.rstrip() + "\n\n" + block + "\n"
    atomic_write_text(md, body)


def write_json(path: Path, obj) -> None:
    from fastneus.io import atomic_write_json

    atomic_write_json(path, obj)
