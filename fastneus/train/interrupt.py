"""Ctrl-C (SIGINT) and SIGTERM during training: stop at the next step boundary, save, exit.

Raising ``KeyboardInterrupt`` wherever the signal lands could leave the optimiser half
stepped or a log line half written. Instead the handler only records the request; the
trainer's loop sees it through ``Trainer.finished()``, ends the step, writes its usual final
checkpoint, and :class:`RunInterrupted` then carries a one-line message (where it saved,
how to continue) to the command line. A second signal stops at once: the checkpoint on disk
is then the last periodic one, still whole because checkpoints are written atomically.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from pathlib import Path
from typing import Iterator

from fastneus.train.checkpoint import CKPT_NAME

SIGNALS = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None)) if s is not None)


class RunInterrupted(KeyboardInterrupt):
    """Training stopped on a signal after saving a consistent checkpoint; ``str()`` says where."""


@contextlib.contextmanager
def stop_on_signal(trainer, out: Path) -> Iterator[None]:
    """Within the block, SIGINT/SIGTERM set ``trainer.stop_signal`` instead of raising.

    On leaving the block after such a request, raises :class:`RunInterrupted`. Signal
    handlers can only be set from the main thread; elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def request_stop(signum, frame):
        if trainer.stop_signal is not None:  # asked twice: stop now
            raise KeyboardInterrupt
        trainer.stop_signal = signal.Signals(signum).name

    previous = {s: signal.signal(s, request_stop) for s in SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    if trainer.stop_signal is not None:
        raise RunInterrupted(f"{trainer.stop_signal} at step {trainer.step}; checkpoint saved in "
                             f"{Path(out) / CKPT_NAME}; continue with --resume")
