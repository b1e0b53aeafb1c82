"""What the benchmark scripts share, so that each script is only its experiment.

- timing: ``sync``, ``time_fn``, ``median``, ``ratio``, ``peak_mem_mb``;
- provenance and outputs: ``machine``, ``git_rev``, ``command_line``, ``provenance`` (the JSON's
  machine/git/command), ``provenance_line`` (the Markdown's), ``write_results`` (JSON + Markdown),
  ``md_table``, ``update_section`` (a generated section of a docs page), ``write_json``;
- scenes and trainers: ``cached_scene`` (synthesise once, then load), ``default_preset``,
  ``parse_sets``, ``make_trainer`` (the real Trainer, built as ``fastneus train`` builds it);
- the real training step phase by phase: ``StepPhases``, ``phase_breakdown``.
"""
from __future__ import annotations

import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
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
    """Short commit of the code measured: ``FASTNEUS_COMMIT`` when set (a copy sent to a GPU
    machine without its ``.git``: git would answer for whatever repository encloses it)."""
    if os.environ.get("FASTNEUS_COMMIT"):
        return os.environ["FASTNEUS_COMMIT"]
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


# ----------------------------------------------------------------------------- small numbers
def median(xs) -> float:
    """Median of ``xs`` (NaN when empty)."""
    xs = list(xs)
    return statistics.median(xs) if xs else float("nan")


def ratio(a: float, b: float) -> float:
    """``a / b`` with ``b`` floored at 1e-9 (speed-ups and shares of tiny timings)."""
    return a / max(b, 1e-9)


def peak_mem_mb(device: str) -> float:
    """GPU: torch's peak allocation since the last reset; CPU: the process's peak RSS (MiB)."""
    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2 ** 20
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


# ----------------------------------------------------------------------------- provenance and outputs
def command_line(script: str, argv: list[str] | None = None) -> str:
    """The command that ran, as a reader would type it: ``python scripts/<script> <args>``."""
    return f"python scripts/{script} " + " ".join(sys.argv[1:] if argv is None else argv)


def provenance(device: str, command: str) -> dict:
    """``{"machine", "git", "command"}``: what every benchmark JSON starts with."""
    return {"machine": machine(device), "git": git_rev(), "command": command}


def provenance_line(device: str, command: str) -> str:
    """One Markdown line naming the machine, commit, date and command of a result."""
    return f"Machine: {machine(device)}; commit {git_rev()}; {time.strftime('%Y-%m-%d')}. Command: `{command}`."


def write_results(out: Path, stem: str, data: dict, text: str, device: str, command: str) -> Path:
    """``out/<stem>.json`` (provenance + ``data``) and ``out/<stem>.md`` (``text``); returns the JSON path."""
    from fastneus.io import atomic_write_text

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{stem}.json", {**provenance(device, command), **data})
    atomic_write_text(out / f"{stem}.md", text.rstrip() + "\n")
    return out / f"{stem}.json"


# ----------------------------------------------------------------------------- scenes and trainers
def default_preset(device: str) -> str:
    """The preset a benchmark uses by default: fewview on CUDA, cpu-quick on CPU."""
    return "fewview" if device.startswith("cuda") else "cpu-quick"


def parse_counts(text: str, flag: str) -> list[int]:
    """``"1,2"`` -> ``[1, 2]``: comma-separated positive integers, else one line naming ``flag``."""
    try:
        vals = [int(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        vals = []
    if not vals or min(vals) < 1:
        raise SystemExit(f"{flag}: expected comma-separated positive integers, got {text!r}")
    return vals


def parse_sets(items: list[str] | None) -> dict[str, str]:
    """``["k=v", ...]`` -> ``{"k": "v"}`` (values stay strings)."""
    out = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"expected key=value, got {it!r}")
        k, v = it.split("=", 1)
        out[k.strip()] = v
    return out


def cached_scene(path: Path, **synth_kw):
    """Synthesise a scene into ``path`` once (``fastneus.synth.render.synthesize(path, **synth_kw)``), then load it."""
    from fastneus.data import Scene
    from fastneus.synth.render import synthesize

    path = Path(path)
    if not (path / "scene.json").is_file():
        synth_kw.setdefault("progress", False)
        synthesize(path, **synth_kw)
    return Scene.load(path)


def make_trainer(scene, device: str, overrides: list[str], out: Path, preset: str | None = None, base=None):
    """The real :class:`fastneus.train.trainer.Trainer`, built as ``fastneus train`` builds it
    (``load_config(preset, overrides)`` then ``Trainer(scene, cfg, out, device)``); logging and
    periodic checkpoints are switched off unless ``overrides`` set them."""
    from fastneus.config import load_config
    from fastneus.train.trainer import Trainer

    cfg = load_config(preset or default_preset(device), ["log_every=1000000", "save_every=100000000"]
                      + list(overrides), base=base)
    return Trainer(scene, cfg, Path(out), device)


# ----------------------------------------------------------------------------- phases of the real step
PHASES = ("ray generation", "marching", "hash encoding", "MLPs", "rendering", "loss + backward", "optimiser",
          "occupancy update")


class StepPhases:
    """Device-synchronised milliseconds per phase of the real ``Trainer.train_step``.

    Nothing of the step is re-implemented: while the context is open, the parts the step calls
    are wrapped with a synchronising timer (``grid.update`` -> occupancy update, ``bank.sample``
    and ``rig.rays`` -> ray generation, the ``march_rays`` op -> marching, the field's
    ``encode``/``encode_jac`` -> hash encoding, ``sdf_and_grad``/``color`` less their encoding ->
    MLPs, ``shade_samples`` less the above -> rendering, the Adam update -> optimiser). What no part
    covers (the loss terms, ``backward``, the NaN guard, gauge fixing) is "loss + backward".
    Time inside the occupancy update (its SDF queries) stays in that phase. The synchronisations
    make a phased step slower than a plain one.
    """

    def __init__(self, tr):
        self.tr, self.device = tr, str(tr.device)
        if getattr(tr, "graphs", None) is not None:  # a replayed graph runs none of the wrapped calls:
            tr.graphs.enabled = False               # the phases are those of the eager step
        self.ms = dict.fromkeys(PHASES, 0.0)
        self._stack: list[list] = []  # [phase, ms spent in nested wrapped calls]
        self._undo: list = []

    def _timed(self, phase: str, fn):
        def wrapped(*a, **k):
            if any(f[0] == "occupancy update" for f in self._stack):
                return fn(*a, **k)
            sync(self.device)
            t = time.perf_counter()
            self._stack.append([phase, 0.0])
            try:
                return fn(*a, **k)
            finally:
                sync(self.device)
                dt = (time.perf_counter() - t) * 1000
                _, inner = self._stack.pop()
                self.ms[phase] += dt - inner
                if self._stack:
                    self._stack[-1][1] += dt
        return wrapped

    def _patch(self, obj, name: str, phase_or_fn) -> None:
        had = name in getattr(obj, "__dict__", {})
        old = getattr(obj, name)
        self._undo.append((obj, name, had, old))
        setattr(obj, name, self._timed(phase_or_fn, old) if isinstance(phase_or_fn, str) else phase_or_fn)

    def __enter__(self) -> "StepPhases":
        import fastneus.field.renderer as renderer
        import fastneus.train.trainer as trainer_mod

        tr = self.tr
        get_op = renderer.get_op
        self._patch(renderer, "get_op", lambda name, backend="warp": self._timed(
            "marching" if name == "march_rays" else "rendering", get_op(name, backend)))
        self._patch(trainer_mod, "shade_samples", "rendering")
        self._patch(tr.grid, "update", "occupancy update")
        self._patch(tr.bank, "sample", "ray generation")
        self._patch(tr.rig, "rays", "ray generation")
        for name in ("encode", "encode_jac"):
            self._patch(tr.field, name, "hash encoding")
        for name in ("sdf_and_grad", "color"):
            self._patch(tr.field, name, "MLPs")
        for name in ("step", "gated_step", "device_update"):  # CPU, CUDA eager, CUDA captured
            self._patch(tr.opt, name, "optimiser")
        return self

    def __exit__(self, *exc) -> None:
        for obj, name, had, old in reversed(self._undo):
            if had:  # a module global or an instance attribute (e.g. field.encode): put it back
                setattr(obj, name, old)
            else:  # a method: drop the instance's wrapper
                delattr(obj, name)
        self._undo.clear()

    def step(self) -> tuple[dict, float, dict | None]:
        """One real training step: (ms per phase, wall ms, the step's record)."""
        self.ms = dict.fromkeys(PHASES, 0.0)
        sync(self.device)
        t = time.perf_counter()
        rec = self.tr.train_step()
        sync(self.device)
        wall = (time.perf_counter() - t) * 1000
        self.ms["loss + backward"] = max(0.0, wall - sum(v for k, v in self.ms.items() if k != "loss + backward"))
        return dict(self.ms), wall, rec


def phase_breakdown(trainers: dict, steps: int, warmup: int = 5) -> dict:
    """Per-phase medians of real training steps for each trainer of ``trainers`` (name -> Trainer),
    the trainers' steps interleaved (A, B, A, B, ...) so a drifting machine load hits all alike.

    The occupancy update runs every ``occ_update_every`` steps: its mean over the timed steps is
    reported (amortised); every other phase is the median. Returns name -> {"steps", "rays",
    "samples_median", "occ_update_every", "step_ms", "total_ms", "phases": [{"phase", "ms", "share_pct"}]}.
    """
    per = {n: {p: [] for p in PHASES} for n in trainers}
    walls = {n: [] for n in trainers}
    samples = {n: [] for n in trainers}
    for i in range(warmup + steps):
        for n, tr in trainers.items():
            with StepPhases(tr) as sp:
                ms, wall, rec = sp.step()
            if i < warmup:
                continue
            for p in PHASES:
                per[n][p].append(ms[p])
            walls[n].append(wall)
            samples[n].append(int(rec["samples"]) if rec else 0)
    res = {}
    for n, tr in trainers.items():
        med = {p: (statistics.fmean(v) if p == "occupancy update" else median(v)) for p, v in per[n].items()}
        total = sum(med.values())
        res[n] = {"steps": steps, "rays": tr.n_rays, "samples_median": median(samples[n]),
                  "occ_update_every": tr.cfg.occupancy.occ_update_every, "step_ms": median(walls[n]), "total_ms": total,
                  "phases": [{"phase": p, "ms": med[p], "share_pct": 100 * ratio(med[p], total)} for p in PHASES]}
    return res
