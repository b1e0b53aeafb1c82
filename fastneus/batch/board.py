"""What a batch shows while it runs: a live table on a terminal (rich), plain lines otherwise
(a cluster job's log), then the summary table; and ``summary.json``."""
from __future__ import annotations

import time
from pathlib import Path

from fastneus.batch.plan import FINAL_STATES, SUMMARY, Job
from fastneus.io import atomic_write_json

PLAIN_EVERY_S = 30.0  # piped output: one progress line per running scene this often
STYLE = {"done": "green", "skipped": "cyan", "failed": "red", "interrupted": "yellow", "running": "bold",
         "queued": "dim"}


def _steps(j: Job) -> str:
    if j.steps is None:
        return "-"
    return f"{j.steps}/{j.total}" if j.total and j.state in ("running", "interrupted") else str(j.steps)


def _time(j: Job) -> str:
    t = j.elapsed()
    if t is None:
        return "-"
    return f"{t:.0f} s" if t < 600 else f"{t / 60:.1f} min"


def _chamfer(j: Job) -> str:
    return "-" if j.chamfer_mm is None else f"{j.chamfer_mm:.3g}"


def _state(j: Job) -> str:
    return {"new": "queued", "resume": "queued"}.get(j.state, j.state)


class Board:
    """The batch's progress: ``changed(job)`` on a state change, ``tick()`` every poll, ``close()`` at the end.

    Args:
        jobs: every job (skipped ones too: the table shows the whole batch).
        console: a rich Console; on a terminal the table is live, else each change is one line.
    """

    def __init__(self, jobs: list[Job], console):
        self.jobs, self.console = jobs, console
        self.plain = not console.is_terminal
        self.next_plain = time.monotonic() + PLAIN_EVERY_S
        self.live = None
        if not self.plain:
            from rich.live import Live  # function-level: with the rest of rich, only when a batch runs

            self.live = Live(self.table(), console=console, refresh_per_second=2, transient=False)
            self.live.start()

    def table(self, errors: bool = True):
        """The rich table of every job: scene, state, worker, steps, time, Chamfer, error."""
        from rich.table import Table

        t = Table(title=None, show_lines=False)
        for col in ("scene", "state", "worker", "steps", "time", "Chamfer mm"):
            t.add_column(col, no_wrap=True, min_width=min(24, max([len(col)] + [len(j.name) for j in self.jobs]))
                         if col == "scene" else len(col) if col != "state" else 11,
                         justify="right" if col in ("steps", "time", "Chamfer mm") else "left")
        errors = errors and self.console.width >= 120  # a narrow terminal: the errors follow the table in full
        if errors:
            t.add_column("error", no_wrap=True, overflow="ellipsis", max_width=self.console.width - 95)
        for j in self.jobs:
            row = [j.name, f"[{STYLE.get(_state(j), '')}]{_state(j)}[/]", j.worker or "-", _steps(j), _time(j),
                   _chamfer(j)]
            t.add_row(*row, *([j.error or ""] if errors else []))
        return t

    def line(self, j: Job) -> str:
        """One plain line for a job's state."""
        parts = [f"{j.name}: {_state(j)}"]
        if j.worker:
            parts.append(f"on {j.worker}")
        if j.steps is not None:
            parts.append(f"steps {_steps(j)}")
        if j.state not in ("queued", "new", "resume") and j.elapsed() is not None:
            parts.append(_time(j))
        if j.chamfer_mm is not None:
            parts.append(f"Chamfer {j.chamfer_mm:.3g} mm")
        if j.error:
            parts.append(j.error)
        return ", ".join(parts)

    def _say(self, text: str) -> None:
        self.console.print(text, markup=False, highlight=False, soft_wrap=True)

    def changed(self, job: Job) -> None:
        if self.plain:
            if job.state != "queued":
                self._say(self.line(job))
        else:
            self.live.update(self.table())

    def tick(self) -> None:
        if not self.plain:
            self.live.update(self.table())
        elif time.monotonic() >= self.next_plain:
            self.next_plain = time.monotonic() + PLAIN_EVERY_S
            for j in self.jobs:
                if j.state == "running":
                    self._say(self.line(j))

    def close(self) -> None:
        """Stop the live table and print the summary (table, then each error in full)."""
        if self.live is not None:
            self.live.update(self.table())
            self.live.stop()
            self.live = None
        else:
            self.console.print(self.table(errors=False))
        counts = count_states(self.jobs)
        self._say("batch: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n))
        for j in self.jobs:
            if j.error:
                self._say(f"  {j.name} ({j.state}): {j.error}")


def count_states(jobs: list[Job]) -> dict:
    """How many jobs ended in each state (a job never started counts as ``not started``)."""
    out = {s: 0 for s in FINAL_STATES + ("not started",)}
    for j in jobs:
        out[j.state if j.state in FINAL_STATES else "not started"] += 1
    return out


def write_summary(out: Path, jobs: list[Job], meta: dict) -> Path:
    """``out/summary.json`` (atomically): the batch's settings (``meta``), counts per state and one
    record per scene (:meth:`Job.record`)."""
    path = Path(out) / SUMMARY
    atomic_write_json(path, {"written_by": "fastneus batch", **meta,
                             "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                             "counts": count_states(jobs), "scenes": [j.record() for j in jobs]})
    return path
