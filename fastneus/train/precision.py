"""The float32 matrix-product precision of the training step (``run.matmul``).

The small networks' GEMMs (hash features -> 64 -> SDF + features, colour 64 x 2) ran as
float32 SIMT kernels on the GPU: ~1 ms of a ~4.2-ms captured step on an H200. TF32 runs them on
the tensor cores with a 10-bit mantissa and float32 range and accumulation (tiny-cuda-nn, which
NeuS2 and instant-NGP train with, uses half precision there). The Warp kernels (hash encoding,
rendering, Adam) are not matrix products and stay float32.

The setting is scoped: :func:`matmul_precision` sets torch's flag for one training step and puts
the old value back, so the mesh export, the metrics and a caller's own code keep their precision.
A captured CUDA graph keeps the kernels chosen when it was captured (inside the step).
"""

from __future__ import annotations

from contextlib import contextmanager

import torch


def resolve_matmul(mode: str, device: torch.device) -> str:
    """``run.matmul`` for ``device``: auto is tf32 on CUDA GPUs with compute capability >= 8
    (Ampere and later), fp32 elsewhere (the CPU has no TF32)."""
    if mode != "auto":
        return "fp32" if device.type != "cuda" else mode
    if device.type != "cuda":
        return "fp32"
    return "tf32" if torch.cuda.get_device_capability(device)[0] >= 8 else "fp32"


@contextmanager
def matmul_precision(mode: str):
    """Within the block, CUDA float32 matmuls use TF32 (``mode == "tf32"``) or full float32.

    Uses ``torch.backends.cuda.matmul.fp32_precision`` where torch has it (2.9+; torch refuses a
    mix of it and the older ``allow_tf32`` flag), else ``allow_tf32``; restores the old value.
    """
    m = torch.backends.cuda.matmul
    if hasattr(m, "fp32_precision"):
        old = m.fp32_precision
        m.fp32_precision = "tf32" if mode == "tf32" else "ieee"
        try:
            yield
        finally:
            m.fp32_precision = old
    else:  # pragma: no cover - torch < 2.9
        old = m.allow_tf32
        m.allow_tf32 = mode == "tf32"
        try:
            yield
        finally:
            m.allow_tf32 = old
