"""What a batch runs: the scenes named on the command line, one run folder each, and what each needs.

Scenes come as folders (or a scene's main file), glob patterns, or text files listing paths
(one a line, ``#`` starts a comment, relative paths are relative to the list's folder). Each
scene gets a run folder ``OUT/<name>``: its folder name made safe (:data:`SAFE_ID`) and unique.
A name stays with its scene across re-runs (the run folder records its scene), so re-running
the same command finds each run again: a finished one (mesh.ply and metrics.json) is skipped,
an interrupted one (a checkpoint, no metrics) is resumed, anything else starts (again).
"""
from __future__ import annotations

import glob
import json
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from fastneus.data.validate import SAFE_ID
from fastneus.errors import FastneusError
from fastneus.io import atomic_write_json, check_no_link, make_out_dir, open_append, safe_dest
from fastneus.train.checkpoint import CKPT_NAME

SUMMARY = "summary.json"
BATCH_MARK = ".fastneus-batch.json"   # in a run folder: the scene the batch trains there
BATCH_LOG = ".fastneus-batch.log"     # in a run folder: the train command's output (all attempts, appended)
# a scene's main file (the folder's name names the run); any other file is a list of scenes
SCENE_FILES = {"scene.json", "transforms.json", "cameras_sphere.npz"}
FINAL_STATES = ("done", "skipped", "failed", "interrupted")
_OVERRIDE = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*=")


@dataclass
class Job:
    """One scene of a batch and its run.

    Attributes:
        scene: the scene's absolute path (folder, or its main file).
        name: the run folder's name under the batch folder.
        run: the run folder.
        state: ``new`` / ``resume`` (planned), ``queued``, ``running``, then one of
            :data:`FINAL_STATES`. resume: the run had a checkpoint (train gets ``--resume``).
        error: the one-line error of a failed or interrupted run.
        worker: where it ran (``gpu 0``, ``cpu 1``, ``ray``).
        steps: the last logged step; ``total``: the run's step count when known.
        seconds: wall time of this batch's attempt (a skipped run: its recorded total).
        chamfer_mm: GT -> reconstruction Chamfer distance (mm) when the scene has ground truth.
    """

    scene: Path
    name: str
    run: Path
    state: str = "new"
    error: str | None = None
    worker: str | None = None
    steps: int | None = None
    total: int | None = None
    seconds: float | None = None
    chamfer_mm: float | None = None
    started: float | None = None
    log_offset: int = 0
    resume: bool = False
    metrics: dict = field(default_factory=dict)

    @property
    def log(self) -> Path:
        return self.run / BATCH_LOG

    def elapsed(self) -> float | None:
        """Seconds of this attempt so far (or its total once ended)."""
        if self.seconds is not None:
            return self.seconds
        return time.monotonic() - self.started if self.started is not None else None

    def record(self) -> dict:
        """The job as summary.json lists it."""
        keep = ("chamfer_gt2rec_mm", "chamfer_sym_mm", "fscore", "depth_err_pct", "psnr_pattern", "train_seconds")
        return {"name": self.name, "scene": str(self.scene), "run": str(self.run), "state": self.state,
                "error": self.error, "worker": self.worker, "steps": self.steps,
                "seconds": None if self.seconds is None else round(self.seconds, 2),
                "chamfer_gt2rec_mm": self.chamfer_mm, "log": str(self.log),
                "metrics": {k: self.metrics[k] for k in keep if k in self.metrics}}


# --------------------------------------------------------------------------- scenes from the command line
def split_overrides(items: list[str]) -> tuple[list[str], list[str]]:
    """Split the positional arguments into scenes and ``key=value`` overrides (an existing path
    that looks like an override stays a scene)."""
    scenes, overrides = [], []
    for it in items:
        (overrides if _OVERRIDE.match(it) and not os.path.lexists(it) else scenes).append(it)
    return scenes, overrides


def _read_list(path: Path) -> list[str]:
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise FastneusError("is not a text list of scene paths (one a line) nor a scene folder", file=path) from None
    except OSError as e:
        raise FastneusError(f"cannot read the list of scenes: {e.strerror}", file=path) from None
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(line if os.path.isabs(line) else str(path.parent / line))
    return out


def expand_scenes(items: list[str]) -> list[Path]:
    """The scenes named by ``items`` (folders, main files, globs, list files), absolute, in order,
    each once.

    Raises:
        FastneusError: a glob that matches nothing, a list that names no scene, or no scene at all.
    """
    found: list[Path] = []

    def add(item: str, depth: int = 0) -> None:
        if glob.has_magic(item):
            hits = sorted(h for h in glob.glob(item) if os.path.isdir(h) or Path(h).name in SCENE_FILES)
            if not hits:
                raise FastneusError("matches no scene folder", file=item, field="SCENE")
            for h in hits:
                add(h, depth)
            return
        p = Path(item)
        if p.is_file() and p.name not in SCENE_FILES and p.suffix != ".npz":
            if depth > 0:
                raise FastneusError("a list of scenes may not name another list", file=item, field="SCENE")
            entries = _read_list(p)
            if not entries:
                raise FastneusError("the list names no scene", file=p, field="SCENE")
            for e in entries:
                add(e, depth + 1)
            return
        found.append(Path(os.path.abspath(p)))  # a missing one fails as its own scene, the others run

    for it in items:
        add(it)
    if not found:
        raise FastneusError("no scene given", field="SCENE")
    return list(dict.fromkeys(found))


# --------------------------------------------------------------------------- run folders
def safe_name(scene: Path) -> str:
    """A run folder name from the scene's folder name: :data:`SAFE_ID` characters, at most 56 of
    them (room for a ``-N`` suffix), no ``..``."""
    base = scene.parent.name if scene.name in SCENE_FILES else scene.name
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", base)
    name = re.sub(r"\.{2,}", ".", name).lstrip("._-")[:56].rstrip(".")
    name = name or "scene"
    assert SAFE_ID.fullmatch(name), name
    return name


def _recorded_scene(run: Path) -> str | None:
    """The scene a run folder belongs to (the batch's mark, else train's run.json)."""
    for f in (run / BATCH_MARK, run / "run.json"):
        try:
            if f.is_symlink() or not f.is_file():
                continue
            d = json.loads(f.read_text())
        except (OSError, ValueError, RecursionError):
            continue
        if isinstance(d, dict) and isinstance(d.get("scene"), str):
            return d["scene"]
    return None


def is_finished(run: Path) -> bool:
    """A finished run: mesh.ply and metrics.json (pipeline.finish_run writes metrics.json after the mesh)."""
    return all((run / n).is_file() and not (run / n).is_symlink() for n in ("mesh.ply", "metrics.json"))


def read_metrics(run: Path) -> dict:
    """The run's metrics.json ({} when missing or unreadable)."""
    try:
        d = json.loads((run / "metrics.json").read_text())
    except (OSError, ValueError, RecursionError):
        return {}
    return d if isinstance(d, dict) else {}


def plan(scenes: list[Path], out: Path) -> list[Job]:
    """One :class:`Job` per scene, its run folder under ``out`` chosen and its state (``skipped`` for a
    finished run, ``resume`` with a checkpoint, else ``new``) read from disk. Nothing is written.

    A name is taken when this batch already gave it, when it is :data:`SUMMARY`, or when ``out/<name>``
    exists and belongs to another scene (or is a link or a file); the next ``<name>-2``, ``-3`` ... is
    tried then.
    """
    out = Path(os.path.abspath(out))
    used: set[str] = {SUMMARY}
    jobs = []
    for scene in scenes:
        base = safe_name(scene)
        for i in range(1, 10 ** 6):
            name = base if i == 1 else f"{base}-{i}"
            if name in used:
                continue
            run = out / name
            if not os.path.lexists(run):
                break
            if run.is_dir() and not run.is_symlink() and _recorded_scene(run) == str(scene):
                break
        used.add(name)
        job = Job(scene=scene, name=name, run=run)
        if is_finished(run):
            job.state = "skipped"
            job.metrics = read_metrics(run)
            job.steps = job.metrics.get("steps")
            job.seconds = (job.metrics.get("timing") or {}).get("total") if isinstance(job.metrics.get("timing"),
                                                                                        dict) else None
            job.chamfer_mm = _chamfer(job.metrics)
        elif (run / CKPT_NAME).is_file():
            job.state, job.resume = "resume", True
        jobs.append(job)
    return jobs


def _chamfer(metrics: dict) -> float | None:
    v = metrics.get("chamfer_gt2rec_mm")
    return float(v) if isinstance(v, (int, float)) and v == v and abs(v) != float("inf") else None


def prepare(job: Job, out: Path) -> None:
    """Create the job's run folder (never through a link), record its scene there, and note where
    this attempt's output starts in the batch log. Call inside ``fastneus.io.confined(out)``."""
    run = safe_dest(out, job.name, field="--out")
    make_out_dir(run)
    check_no_link(run)
    if _recorded_scene(run) is None:
        atomic_write_json(run / BATCH_MARK, {"written_by": "fastneus batch", "scene": str(job.scene)})
    with open_append(job.log) as f:
        f.write(f"=== fastneus batch: {time.strftime('%Y-%m-%d %H:%M:%S')} {'resume' if job.resume else 'train'} "
                f"{job.scene}\n")
        job.log_offset = f.tell()


def open_log(job: Job):
    """The job's batch log, opened for appending (never through a link): the train command's output."""
    return open_append(job.log)


def train_args(job: Job, config: str | None, device: str | None, threads: int | None,
               overrides: list[str]) -> list[str]:
    """The ``fastneus train`` arguments (after ``python -m fastneus``) for ``job``: ``--resume`` for an
    interrupted run (its own config.yaml; ``--config`` is not passed then), the same options otherwise."""
    args = ["train", str(job.scene), "--out", str(job.run)]
    if job.resume:
        args.append("--resume")
    elif config:
        args += ["--config", config]
    if device:
        args += ["--device", device]
    if threads:
        args += ["--threads", str(threads)]
    return args + list(overrides)


def python_command(args: list[str]) -> list[str]:
    """``python -m fastneus ARGS`` with this interpreter."""
    return [sys.executable, "-m", "fastneus", *args]


# --------------------------------------------------------------------------- progress and outcome from disk
def read_progress(job: Job) -> None:
    """Update ``job.steps`` / ``job.total`` from the last line of the run's log.jsonl."""
    path = job.run / "log.jsonl"
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - 4096))
            lines = f.read().splitlines()
    except OSError:
        return
    for raw in reversed(lines):
        try:
            rec = json.loads(raw)
        except (ValueError, RecursionError):
            continue  # a line being written
        if isinstance(rec, dict) and isinstance(rec.get("step"), int):
            job.steps = rec["step"]
            p = rec.get("progress")
            if isinstance(p, (int, float)) and 0 < p <= 1:
                job.total = int(round(rec["step"] / p))
            return


def error_line(job: Job) -> str:
    """The one-line error of this attempt: train's ``fastneus train: ...`` line, else the last line it printed."""
    try:
        with open(job.log, "rb") as f:
            f.seek(job.log_offset)
            text = f.read()[-65536:].decode("utf-8", "replace")
    except OSError as e:
        return f"(no output: {e.strerror})"
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if ln.startswith("fastneus train:"):
            ln = ln[len("fastneus train:"):].strip()
            return ln[len("error:"):].strip() if ln.startswith("error:") else ln
    return lines[-1][:500] if lines else "(no output)"


def conclude(job: Job, rc: int | None, stopping: bool) -> None:
    """Set the job's final state from the train command's exit status and its run folder."""
    read_progress(job)
    if rc == 0 and is_finished(job.run):
        job.state, job.error = "done", None
        job.metrics = read_metrics(job.run)
        job.steps = job.metrics.get("steps", job.steps)
        job.chamfer_mm = _chamfer(job.metrics)
    elif stopping or rc in (130, -2, -15):
        job.state = "interrupted"
        saved = (job.run / CKPT_NAME).is_file()
        job.error = "stopped" + ("; checkpoint saved: the same command resumes it" if saved else " before a checkpoint")
    else:
        job.state = "failed"
        job.error = error_line(job) if rc != 0 else "train exited 0 but left no mesh.ply / metrics.json"
