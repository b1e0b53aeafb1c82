"""Progress a user can follow while a run trains: small validation renders in the run folder and,
when the ``tensorboard`` package is installed, TensorBoard event files.

Every ``every_s`` seconds of training (or ``every_steps`` steps), one held frame (the first frame
not trained on, else the first training frame) is rendered at a small size and written as
``RUN/validation/step_000123.png``: photo | render with the pattern | depth, with the step and the
panel's PSNR in a caption bar. Validation renders take no training time (the caller keeps them
out of the clock), use no random numbers and change no parameter, so a run with them trains
exactly as one without.

TensorBoard (``pip install 'fastneus[tensorboard]'``): the scalars of each log record go to
``RUN/tensorboard/`` under ``train/<key>`` and each validation panel as an image. Without the
package nothing is imported (its absence is found with :func:`importlib.util.find_spec`).

Writes go through :mod:`fastneus.io` (atomic, never through a symbolic link inside the run folder).
"""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import torch

from fastneus.errors import FastneusError
from fastneus.field.renderer import render_image
from fastneus.io import atomic_write_image, check_no_link, confined
from fastneus.train.rays import RayBank, build_projection

VALIDATION_DIR = "validation"
TENSORBOARD_DIR = "tensorboard"
# TensorBoard's writer opens once this much training has run (or at the end, after mesh.ply):
# importing it takes 0.3-1 s, which landed before a short run's mesh.ply (an H200's 3-s run: the
# train phase 3.3 s for 3.0 s of steps). Until then the log records wait in memory.
TB_OPEN_AFTER_S = 10.0
CAPTION_PX = 14  # height of the caption bar over the panels


def tensorboard_available() -> bool:
    """Whether the ``tensorboard`` package is installed (found without importing it)."""
    return importlib.util.find_spec("tensorboard") is not None


def held_frame(scene, train_frames: list[int]) -> int:
    """The frame validation renders: the first frame not trained on, else the first training frame."""
    used = set(train_frames)
    held = [i for i in range(len(scene.frames)) if i not in used]
    return held[0] if held else train_frames[0]


def panel_size(w: int, h: int, size: int) -> tuple[int, int]:
    """(w, h) scaled so the longer side is at most ``size`` (never enlarged, at least 1 pixel)."""
    s = min(1.0, size / max(w, h))
    return max(1, round(w * s)), max(1, round(h * s))


def _u8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def depth_panel(depth: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8: near bright, far dark where the surface is solid (opacity > 0.5), else black."""
    solid = opacity > 0.5
    out = np.zeros(depth.shape, np.float32)
    if solid.any():
        lo, hi = np.percentile(depth[solid], [1, 99])
        out = np.where(solid, 1.0 - 0.8 * np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1), 0.0)
    return np.repeat(_u8(out)[..., None], 3, -1)


class ProgressWriter:
    """Validation renders every N seconds or steps, and TensorBoard scalars when installed.

    Args:
        trainer: a :class:`fastneus.train.trainer.Trainer` (reads ``scene``, ``cfg``, ``frames``,
            ``field``, ``grid``, ``rig``, ``device``, ``out`` and ``illumination()``; changes nothing).
        every_s: seconds of training between validation renders; 0 turns the time trigger off.
        every_steps: steps between validation renders; 0 turns the step trigger off. With both
            off, only ``maybe_validate(..., force=True)`` renders.
        size: longest side of each panel in pixels.
        frame: the scene frame to render (default :func:`held_frame`).
        tensorboard: ``"auto"`` (when the package is installed), ``"on"`` (an error without it) or
            ``"off"``.
    Raises:
        FastneusError: a bad setting, or ``tensorboard="on"`` without the package.
    """

    def __init__(self, trainer, every_s: float = 60.0, every_steps: int = 0, size: int = 160,
                 frame: int | None = None, tensorboard: str = "auto"):
        if not (math.isfinite(every_s) and every_s >= 0) or every_steps < 0 or size < 8:
            raise FastneusError(f"bad validation setting: every_s={every_s}, every_steps={every_steps}, size={size}",
                                field="validate_every")
        if tensorboard not in ("auto", "on", "off"):
            raise FastneusError(f"expected auto, on or off, got {tensorboard!r}", field="tensorboard")
        self.tr = trainer
        self.out = Path(trainer.out)
        self.every_s, self.every_steps, self.size = float(every_s), int(every_steps), int(size)
        self.frame = held_frame(trainer.scene, list(trainer.frames)) if frame is None else int(frame)
        if not 0 <= self.frame < len(trainer.scene.frames):
            raise FastneusError(f"frame {self.frame} out of range 0..{len(trainer.scene.frames) - 1}",
                                field="validate_frame")
        # intervals count from where the trainer stands (0 for a new run, the checkpoint's on --resume)
        self.last_s = float(getattr(trainer, "elapsed", 0.0))  # training seconds at the last validation
        self.last_step = int(getattr(trainer, "step", 0))
        self.written: list[Path] = []         # validation images, in order
        self._bank = None                     # (RayBank, projection) of the frame when poses are fixed
        self._bank_blur = 0.0                 # the pattern blur that projection was built with
        self.tb = None
        if tensorboard == "on" and not tensorboard_available():
            raise FastneusError("the tensorboard package is not installed (pip install 'fastneus[tensorboard]')",
                                field="tensorboard")
        # opened by _writer(): after TB_OPEN_AFTER_S of training, at a validation render or at the end
        self._tb_wanted = tensorboard != "off" and tensorboard_available()
        self._tb_pending: list[tuple[int, dict]] = []  # log records before the writer opened
        if self._tb_wanted:  # the folder is checked now: a link in its place is refused before training
            with confined(self.out):
                check_no_link(self.out / TENSORBOARD_DIR / "events")

    # ------------------------------------------------------------------ TensorBoard
    def _open_tensorboard(self):
        d = self.out / TENSORBOARD_DIR
        with confined(self.out):
            # checked again here: the writer opens late, and a link planted since is refused too
            check_no_link(d / "events")
        # torch.utils.tensorboard imports the tensorboard package (~1 s): only here, only when installed
        from torch.utils.tensorboard import SummaryWriter

        d.mkdir(parents=True, exist_ok=True)
        return SummaryWriter(log_dir=str(d))

    def _writer(self):
        """The TensorBoard writer, opened now if wanted and not yet open (the records logged so
        far are written first); None without TensorBoard."""
        if self.tb is None and self._tb_wanted:
            self.tb = self._open_tensorboard()
            pending, self._tb_pending = self._tb_pending, []
            for step, record in pending:
                self._scalars(step, record)
        return self.tb

    def on_log(self, step: int, record: dict) -> None:
        """Record one log record (the dict the trainer appends to log.jsonl): each finite number
        becomes a TensorBoard scalar ``train/<key>``; a no-op without TensorBoard. Before
        :data:`TB_OPEN_AFTER_S` seconds of training (``record["time"]``) the record waits in memory."""
        if not self._tb_wanted:
            return
        if self.tb is None and float(record.get("time", 0.0)) < TB_OPEN_AFTER_S:
            self._tb_pending.append((int(step), dict(record)))
            return
        if self._writer() is not None:
            self._scalars(step, record)

    def _scalars(self, step: int, record: dict) -> None:
        for k, v in record.items():
            if k in ("step", "time") or isinstance(v, bool) or not isinstance(v, (int, float)):
                continue
            if math.isfinite(v):
                self.tb.add_scalar(f"train/{k}", v, step)
        if "time" in record:
            self.tb.add_scalar("train/seconds", record["time"], step)

    # ------------------------------------------------------------------ validation renders
    @property
    def enabled(self) -> bool:
        """Whether validation renders are on (a time or a step interval is set)."""
        return self.every_s > 0 or self.every_steps > 0

    def due(self, step: int, elapsed_s: float) -> bool:
        """Whether a validation render is due at ``step`` after ``elapsed_s`` seconds of training."""
        if self.every_s > 0 and elapsed_s - self.last_s >= self.every_s:
            return True
        return self.every_steps > 0 and step - self.last_step >= self.every_steps

    def maybe_validate(self, step: int, elapsed_s: float, force: bool = False) -> Path | None:
        """Render the held frame when due (or ``force``); returns the image written, else None.

        Args:
            step: the trainer's step count.
            elapsed_s: seconds of training so far (the trainer's ``elapsed``).
            force: render now (e.g. at the end of the run), whatever the interval.
        """
        if not (force or self.due(step, elapsed_s)):
            return None
        self.last_s, self.last_step = float(elapsed_s), int(step)
        img, psnr = self.render()
        img = self._captioned(img, f"step {step}  {elapsed_s:.0f} s  frame {self.frame}  psnr {psnr:.1f} dB")
        path = self.out / VALIDATION_DIR / f"step_{step:06d}.png"
        with confined(self.out):
            atomic_write_image(path, img)
        self.written.append(path)
        if self._writer() is not None:
            self.tb.add_image("validation/photo_render_depth", img, step, dataformats="HWC")
            self.tb.add_scalar("validation/psnr", psnr, step)
            self.tb.flush()
        return path

    def _frame_data(self):
        """(RayBank, projection) of the validation frame, with what the rig has learned so far
        (poses are rebuilt each time while pose refinement is on)."""
        tr = self.tr
        rig = getattr(tr, "rig", None)
        blur = getattr(tr, "pattern_blur", 0.0)
        if self._bank is not None and self._bank_blur == blur:  # camera_blur=auto may change it mid-run
            return self._bank
        posed_on = rig is not None and rig.pose_on
        scene = rig.eval_scene() if posed_on else tr.scene
        refr = tr.cfg.rig.refraction
        bank = RayBank(scene, [self.frame], tr.device, refraction=refr)
        proj = build_projection(scene, [self.frame], tr.device, refraction=refr,
                                camera_blur=blur)
        if not posed_on:
            self._bank, self._bank_blur = (bank, proj), blur
        return bank, proj

    @torch.no_grad()
    def render(self) -> tuple[np.ndarray, float]:
        """The panel [h, 3w + 4, 3] uint8 (photo | render | depth) and its PSNR in dB."""
        import cv2

        tr, cfg = self.tr, self.tr.cfg
        bank, proj = self._frame_data()
        rig = getattr(tr, "rig", None)
        if rig is not None:
            proj = rig.light_model(proj)  # learned projector blur, water
        W, H = (int(x) for x in bank.wh[0].tolist())
        w, h = panel_size(W, H, self.size)
        row, col = torch.meshgrid(torch.arange(h, device=bank.device), torch.arange(w, device=bank.device),
                                  indexing="ij")
        u = (col.reshape(-1).float() + 0.5) * (W / w)  # the small panel's pixel centres, full-size pixels
        v = (row.reshape(-1).float() + 0.5) * (H / h)
        fidx = torch.zeros(u.shape[0], dtype=torch.int64, device=bank.device)
        o, d = bank.rays(fidx, u, v)
        i_r, i_b = (x.detach() for x in tr.illumination())
        r = render_image(tr.field, tr.grid.bits, tr.grid.resolution, proj, o, d, fidx.to(torch.int32), cfg,
                         i_r=i_r, i_b=i_b)
        if rig is not None:
            color = rig.composite(r["color"], r, cfg.rays.background)
        else:
            color = r["color"] + cfg.rays.background * (1 - r["opacity"])[:, None]
        color = (color / float(getattr(tr, "photo_gain", 1.0))).clamp(0, 1).cpu().numpy().reshape(h, w, 3)
        photo = bank.image(0).cpu().numpy()
        if (w, h) != (W, H):
            photo = cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)
        depth = (r["depth"] / r["opacity"].clamp_min(1e-6)).numpy().reshape(h, w)
        mse = float(np.mean((color - photo / 255.0) ** 2))
        psnr = -10.0 * math.log10(max(mse, 1e-10))
        gap = np.full((h, 2, 3), 255, np.uint8)
        panel = np.concatenate([photo, gap, _u8(color), gap, depth_panel(depth, r["opacity"].numpy().reshape(h, w))],
                               axis=1)
        return panel, psnr

    @staticmethod
    def _captioned(img: np.ndarray, text: str) -> np.ndarray:
        """``img`` under a white bar holding ``text`` (small, black)."""
        import cv2

        bar = np.full((CAPTION_PX, img.shape[1], 3), 255, np.uint8)
        cv2.putText(bar, text, (3, CAPTION_PX - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
        return np.concatenate([bar, img], axis=0)

    def finish(self, step: int, elapsed_s: float) -> Path | None:
        """End of training: a last validation render (when validation is on and none was made at
        this step), then :meth:`close`. Returns the image written, if any."""
        path = None
        if self.enabled and not (self.written and self.last_step == step):
            path = self.maybe_validate(step, elapsed_s, force=True)
        self.close()
        return path

    def close(self) -> None:
        """Flush and close the TensorBoard writer (validation images are complete when written);
        records still waiting open it first."""
        if self._tb_pending:
            self._writer()
        self._tb_wanted = False  # closed for good
        if self.tb is not None:
            self.tb.close()
            self.tb = None
