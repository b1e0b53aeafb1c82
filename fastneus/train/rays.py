"""Random (frame, pixel) batches -> rays in normalised coordinates.

Images are kept once as uint8 (one flat store for all frames, whatever their sizes),
so memory grows with the pixels on disk, never with float copies per pattern.
Projectors are flattened to per-(frame, projector) matrices and one shared
:class:`fastneus.kernels.render.PatternStore` holding each distinct pattern once.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from fastneus.errors import FastneusError
from fastneus.kernels.render import PatternStore
from fastneus.data.kinds import get_projector_kind, projector_kinds

SATURATED = 254  # a photo channel at or above this code is (probably) clipped by the camera


def background_codes(lut: torch.Tensor, background: float, tol: float) -> torch.Tensor:
    """[256] bool: the 8-bit codes whose decoded (linear) value is within ``tol`` of ``background``."""
    return (lut - float(background)).abs() <= float(tol) + 1e-7


def backdrop_noise(codes: torch.Tensor, lut: torch.Tensor | None, background: float) -> float:
    """Median over pixels of the largest per-channel distance of the decoded value from
    ``background`` (a deterministic subsample of at most 2^20 pixels). In a dark room the
    median pixel is backdrop, and this is its noise floor: a real camera's read noise puts
    black pixels a few thousandths above 0 (synth --realistic: median 0.004 linear).

    Args:
        codes: [N, 3] uint8 pixel codes; lut: [256] decoded value per code, or None (linear,
            code / 255); background: the background colour in [0, 1].
    """
    flat = codes.reshape(-1, 3)
    if flat.shape[0] == 0:
        return 0.0
    sub = flat[:: max(1, flat.shape[0] // (1 << 20))].long().cpu()
    values = lut.float().cpu() if lut is not None else torch.arange(256, dtype=torch.float32) / 255.0
    return float((values - float(background)).abs()[sub].amax(1).median())


def backdrop_tolerance(floor: float, k: float, noise: float, cap: float) -> float:
    """The per-channel distance from the background colour still counted as background:
    ``floor`` (``loss.bg_tolerance``), widened to ``k`` times the photos' noise floor
    (:func:`backdrop_noise`; ``loss.bg_noise_k``, 0 = never) but not past ``cap`` (the
    foreground threshold: no pixel is both). A median pixel farther than ``cap`` from the
    background is not backdrop (a lit backdrop, a scene filling the frame): then ``floor``."""
    if k <= 0 or noise > cap:
        return float(floor)
    return float(max(floor, min(k * noise, cap)))


LIT_ROOM = 0.15  # median brightness of the above-threshold pixels that makes a lit room (foreground_flags)


SOLID = 0.5  # share of the above-threshold pixels inside a 3 x 3 block of them that makes a lit room


def _brightness(codes: torch.Tensor, lut: torch.Tensor | None, background: float) -> torch.Tensor:
    """[N] the brightest channel of each pixel (linear) above ``background``."""
    values = lut if lut is not None else torch.arange(256, dtype=torch.float32, device=codes.device) / 255.0
    return values[codes.long()].amax(1) - float(background)


def _per_frame(sizes: list[tuple[int, int]]):
    """(the frame's rows of the concatenated pixels, H, W) for each frame of (W, H) ``sizes``."""
    o = 0
    for w, h in sizes:
        yield slice(o, o + w * h), h, w
        o += w * h


def _bright_objects(bright: torch.Tensor, above: torch.Tensor) -> bool:
    """The pixels above the background (``above``) have a median brightness of at least
    :data:`LIT_ROOM` (in a dark room the ambient-lit object is far dimmer than the laser lines)."""
    return bool(above.any()) and float(bright[above].median()) >= LIT_ROOM


def lit_room(codes: torch.Tensor, lut: torch.Tensor | None, background: float, threshold: float,
             sizes: list[tuple[int, int]]) -> bool:
    """Whether the photos show a lit room rather than lasers in the dark: the pixels more than
    ``threshold`` above the background are bright (median >= :data:`LIT_ROOM`) *and* form solid
    regions (>= :data:`SOLID` of them inside a 3 x 3 block of such pixels). In a dark room either
    the object's ambient-lit pixels are far dimmer than the laser lines, or, where they stay under
    the threshold, only the lines count, and lines are thin.

    Args:
        codes: [sum HW, 3] uint8, frames concatenated; lut: [256] decoding or None (linear);
            background: in [0, 1]; threshold: linear; sizes: (W, H) per frame.
    """
    bright = _brightness(codes, lut, background)
    above = bright > threshold
    if not _bright_objects(bright, above):
        return False
    inside = 0
    for rows, h, w in _per_frame(sizes):
        a = above[rows].reshape(1, 1, h, w).float()
        inside += int((-torch.nn.functional.max_pool2d(-a, 3, stride=1, padding=1) > 0.5).sum())
    return inside >= SOLID * int(above.sum())


def foreground_flags(codes: torch.Tensor, lut: torch.Tensor | None, background: float, threshold: float,
                     relative: float, sizes: list[tuple[int, int]]) -> torch.Tensor:
    """[sum HW] bool: pixels clearly brighter than the background, read off the photos (the
    foreground prior's 'the object is here'): the brightest channel more than ``threshold``
    above ``background`` *and* at least ``relative`` times the brightest pixel within 2 px.
    The second test drops the lens's halo around a bright object (a defocused camera spreads a
    lit surface 1-2 px onto the backdrop; flagged, the prior fattened the realistic ant in
    Normal light: 7.7 -> 14.2 mm) but keeps a thin dim part, which is its own neighbourhood's
    brightest pixel.

    Args:
        codes: [sum HW, 3] uint8, frames concatenated; lut: [256] or None (linear codes);
        background: in [0, 1]; threshold: linear; relative: in (0, 1]; sizes: (W, H) per frame.
    """
    bright = _brightness(codes, lut, background)                                 # [sum HW]
    out = bright > threshold
    # a lit room only: in a dark one the object's ambient-lit pixels are far dimmer than the laser
    # lines crossing it and would fail the relative test (realistic ant Dark: 6.0 -> 40.8 mm)
    if not _bright_objects(bright, out):
        return out
    for rows, h, w in _per_frame(sizes):
        v = bright[rows].reshape(1, 1, h, w)
        near = torch.nn.functional.max_pool2d(v, 5, stride=1, padding=2)
        out[rows] &= (v >= relative * near).reshape(-1)
    return out


PHOTO_MASK_SPECK = 6  # px: a non-background blob smaller than this is the photo's noise, not the object


def photo_masks(bank, frames: list[int]) -> dict[int, np.ndarray] | None:
    """Masks read off the photos of a dark room (no masks on disk): every pixel the backdrop flags do
    not claim (the lit and the ambient-lit object, the lens's halo), less specks under
    :data:`PHOTO_MASK_SPECK` px (noise over the backdrop's tolerance), dilated by a pixel.

    Args:
        bank: a :class:`RayBank` with background flags (``bg``); frames: scene frame index per bank
            frame (the trainer's ``frames``).
    Returns:
        {frame: foreground [H, W] bool}, or None without background flags.
    """
    import cv2

    if getattr(bank, "bg", None) is None or not hasattr(bank, "wh"):
        return None
    out = {}
    for a, i in enumerate(frames):
        w, h = (int(x) for x in bank.wh[a].tolist())
        o = int(bank.offset[a])
        nb = (~bank.bg[o:o + w * h].reshape(h, w).bool()).cpu().numpy().astype(np.uint8)
        n, lab, st, _ = cv2.connectedComponentsWithStats(nb, connectivity=8)
        keep = np.zeros(n, bool)
        keep[1:] = st[1:, cv2.CC_STAT_AREA] >= PHOTO_MASK_SPECK
        out[i] = cv2.dilate(keep[lab].astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return out


def trim_halo(fg: torch.Tensor, bg: torch.Tensor, bright: torch.Tensor, sizes: list[tuple[int, int]],
              share: float) -> torch.Tensor:
    """[sum HW] bool: the foreground flags without the lens's halo in a dark room: a flagged pixel
    beside a backdrop pixel (4-neighbour) under ``share`` times the brightest flagged pixel within
    1 px (itself included) is dropped (``share`` > 1: every flagged pixel beside the backdrop).

    A blurred camera spreads the object ~1 px onto the backdrop; where the object is bright enough,
    that ring clears the flags' threshold and the foreground prior pulls it solid, fattening thin
    parts (realistic ant, Dark, no masks: 27 % of the 1-px ring outside the true silhouette flagged).
    The lit room's 5-px ratio test does not serve here: the laser lines crossing the object are many
    times its ambient-lit brightness. A dropped pixel is neither flag (no pull either way).

    Args:
        fg, bg: [sum HW] bool foreground / backdrop flags; bright: [sum HW] brightness above the
            background (linear); sizes: (W, H) per frame; share: in (0, 2].
    """
    out = fg.clone()
    cross = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], device=fg.device).view(1, 1, 3, 3)
    for rows, h, w in _per_frame(sizes):
        f = fg[rows].reshape(1, 1, h, w)
        beside = torch.nn.functional.conv2d(bg[rows].reshape(1, 1, h, w).float(), cross, padding=1) > 0.5
        v = bright[rows].reshape(1, 1, h, w)
        near = torch.nn.functional.max_pool2d(torch.where(f, v, torch.zeros_like(v)), 3, stride=1, padding=1)
        out[rows] &= ~(f & beside & (v < share * near)).reshape(-1)
    return out


def halo_radius(sigma: float) -> int:
    """Pixels of the lens's halo around an object for a camera blur of ``sigma`` px: ceil(2 sigma)
    (a Gaussian edge has fallen to ~2 % of the step there); 0 for a sharp capture."""
    return int(math.ceil(2.0 * sigma - 1e-6)) if sigma > 0 else 0


def halo_weights(codes: torch.Tensor, lut: torch.Tensor | None, background: float, fg: torch.Tensor,
                 bg: torch.Tensor, sizes: list[tuple[int, int]], radius: int, share: float) -> torch.Tensor:
    """[sum HW] uint8 background weight x 255 of each pixel: 255 where ``bg`` flags it; in the band of
    ``radius`` px beside the backdrop, a pixel neither flag claims that is under ``share`` of the
    brightest pixel within 2 px weighs ``1 - ratio / share``; 0 elsewhere.

    A blurred camera spreads a lit object 1-2 px onto the backdrop (the halo). Its pixels are
    neither backdrop nor object, so nothing kept the rays through them empty and the surface
    grew into them (realistic ant, Normal light, no masks: the legs 2-3x their width). A pixel
    whose centre lies outside the object's blurred edge holds under half of the object's
    brightness (a symmetric blur of an edge is at half height over the edge: ``share`` 0.5, the
    foreground flags' own ratio, leaves no pixel claimed by neither), and a thin part is its own
    neighbourhood's brightest pixel (ratio 1: weight 0).

    Args:
        codes: [sum HW, 3] uint8, frames concatenated; lut: [256] or None (linear codes);
        background: in [0, 1]; fg, bg: [sum HW] bool flags (:func:`foreground_flags`, the
        backdrop's); sizes: (W, H) per frame; radius: the band's width in px (0: no band);
        share: in (0, 1].
    """
    out = bg.to(torch.uint8) * 255
    if radius <= 0 or share <= 0:
        return out
    bright = _brightness(codes, lut, background)
    pool = torch.nn.functional.max_pool2d
    for rows, h, w in _per_frame(sizes):
        v = bright[rows].reshape(1, 1, h, w)
        ratio = (v / pool(v, 5, stride=1, padding=2).clamp(min=1e-6)).clamp(0.0, 1.0)
        b = bg[rows].reshape(1, 1, h, w)
        band = (pool(b.float(), 2 * radius + 1, stride=1, padding=radius) > 0) & ~b & ~fg[rows].reshape(1, 1, h, w)
        wt = ((1.0 - ratio / share).clamp(0.0, 1.0) * 255).round().to(torch.uint8)
        out[rows] = torch.where(band, wt, out[rows].reshape(1, 1, h, w)).reshape(-1)
    return out


# the photos' level (illum.level=auto): where the brightest 0.1 % of pixels lie, linear. The
# priors' thresholds and the loss's balance against the eikonal and mask terms were set on captures
# whose level is 0.11-0.25 (dark rooms) to 1 (lit ones); a 4x underexposed dark room (level 0.048)
# without masks came out as a few fragments (GT->rec 442 mm; 12.2 mm scaled to 0.18, 13.1 mm to
# 0.12). Photos under LEVEL_LOW are trained at a level that rises from LEVEL_LOW to LEVEL_REF as
# theirs falls to LEVEL_LOW / 2 (continuous: a capture just under LEVEL_LOW changes by little)
LEVEL_LOW = 0.12
LEVEL_REF = 0.18
LEVEL_MAX_GAIN = 16.0


# a camera's black level (illum.black=auto): the photos' most common value when it is a dark floor
BLACK_MAX = 0.08     # linear: a pedestal, not a grey backdrop or a dark surface
BLACK_SHARE = 0.25   # of the pixels within [0.8, 1.25] x of it (the backdrop of a dark room)
BLACK_BELOW = 0.005  # at most this share darker than half of it: nothing lies under a pedestal


def photo_histogram(scene, frames: list[int], max_frames: int = 8) -> np.ndarray:
    """[256] int64 counts of the pixels' brightest channel code over up to ``max_frames`` of
    ``frames`` spread evenly."""
    pick = [frames[int(k)] for k in np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round())]
    hist = np.zeros(256, dtype=np.int64)
    for i in pick:
        hist += np.bincount(scene.image(i).max(axis=2).ravel(), minlength=256)
    return hist


def photo_level(hist: np.ndarray, lut: np.ndarray | None) -> float:
    """The 99.9th percentile of the pixels' brightest channel (linear, through ``lut``; None = code
    / 255) in :func:`photo_histogram` ``hist``: where the bright laser lines or the lit surface lie,
    whatever share of the image the object fills."""
    code = int(np.searchsorted(np.cumsum(hist), 0.999 * hist.sum()))
    return float(lut[code]) if lut is not None else code / 255.0


def black_level(hist: np.ndarray, lut: np.ndarray | None) -> float:
    """A camera's black level (a raw sensor's pedestal) from :func:`photo_histogram`, linear; 0
    when there is none. The most common value is one when it is dark (<= :data:`BLACK_MAX`), a
    quarter of the pixels or more lie near it (a dark room's backdrop) and almost none below half
    of it: a dark surface or shadow has darker pixels around it, a pedestal has none. The
    background prior looks for the backdrop at 0: over a pedestal of 3 % it found none, and the run
    without masks came out as fragments (259 mm; 12.5 mm with the pedestal taken off)."""
    vals = lut.astype(np.float64) if lut is not None else np.arange(256) / 255.0
    m = int(np.argmax(hist))
    b = float(vals[m])
    if not 0 < b <= BLACK_MAX:
        return 0.0
    n = max(int(hist.sum()), 1)
    near = hist[(vals >= 0.8 * b) & (vals <= 1.25 * b)].sum() / n
    below = hist[vals < 0.5 * b].sum() / n
    return b if near >= BLACK_SHARE and below <= BLACK_BELOW else 0.0


def level_gain(level: float) -> float:
    """The photos' gain for training (illum.level=auto): 1 at or above :data:`LEVEL_LOW`; below it
    the trained level rises linearly from :data:`LEVEL_LOW` to :data:`LEVEL_REF` as ``level`` falls
    to half of :data:`LEVEL_LOW`, and stays at :data:`LEVEL_REF` under that; at most
    :data:`LEVEL_MAX_GAIN` (1 for an all-black capture)."""
    if level >= LEVEL_LOW or level <= 0:
        return 1.0
    half = 0.5 * LEVEL_LOW
    target = LEVEL_REF if level <= half else LEVEL_LOW + (LEVEL_REF - LEVEL_LOW) * (LEVEL_LOW - level) / half
    return float(min(target / level, LEVEL_MAX_GAIN))


def training_lut(scene, frames: list[int], lut: np.ndarray | None, level: str = "auto",
                 black: str = "auto") -> tuple[np.ndarray | None, float, float, str | None]:
    """The decode table the ray bank reads the photos through: the response's ``lut`` (None =
    linear), with a raw camera's black level taken off (``illum.black``, :func:`black_level`) and
    a dim capture scaled up (``illum.level``, :func:`level_gain`), both from one
    :func:`photo_histogram`.

    Returns:
        (lut [256] float32 or None when nothing changed, gain, black level (linear), the run
        summary's line or None).
    """
    if "auto" not in (level, black):
        return lut, 1.0, 0.0, None
    hist = photo_histogram(scene, frames)
    base = lut if lut is not None else (np.arange(256) / 255.0).astype(np.float32)
    notes, gain, pedestal = [], 1.0, black_level(hist, lut) if black == "auto" else 0.0
    if pedestal > 0:
        base = np.clip((base - pedestal) / (1.0 - pedestal), 0.0, 1.0).astype(np.float32)
        notes.append(f"black level: auto -> {pedestal:.3g} (linear; most pixels sit on it, none below): subtracted")
    if level == "auto":
        lvl = photo_level(hist, base)
        gain = level_gain(lvl)
        if gain > 1.0:
            base = np.minimum(base * gain, 1.0).astype(np.float32)
            notes.append(f"photo level: auto -> the brightest 0.1 % of pixels at {lvl:.3g} (linear), under "
                         f"{LEVEL_LOW:g}: trained {gain:.3g}x brighter; i_b, textures and colours are reported in "
                         "the photos' units")
    return (base, gain, pedestal, "; ".join(notes)) if notes else (lut, 1.0, 0.0, None)


def lut_mean(hist: torch.Tensor, lut: torch.Tensor, n: int) -> torch.Tensor:
    """[3] mean decoded colour from per-channel code histograms ``hist`` [3, 256] of ``n`` pixels."""
    return ((hist.double() @ lut.double().cpu()) / max(1, n)).float()


def normalised_camera(scene, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K^-1 [3,3], R_c2w [3,3], origin [3] in normalised space) of frame i."""
    cam = scene.frame_camera(i)
    c2w = np.asarray(scene.cam_to_world(i), dtype=np.float64)
    b = scene.bounds
    origin = (c2w[:3, 3] - np.asarray(b.center, dtype=np.float64)) / float(b.radius)
    return np.linalg.inv(np.asarray(cam.K, dtype=np.float64)), c2w[:3, :3], origin


@dataclass
class Projection:
    """Per-frame projector data for the render kernel.

    Attributes:
        K: [F, P, 3, 3] projector intrinsics.
        W: [F, P, 3, 4] normalised point -> projector camera coordinates.
        pattern: [F, P] int32 index into ``store`` (-1 = off).
        store: all distinct patterns, packed once.
        blur: [P, n*n] per-projector pattern blur taps (fastneus.train.rig), None = plain sampling.
        lights: per emitter kind present in the scene (``fastneus.data.kinds``, registration
            order): ``(on, packed)``, on [F, P] int32 = 1 where projector k is of that kind and lit
            in frame f, packed = the kind's pack hook of the projectors (its light op's input).
            ``laser_on`` and ``planes`` read the laser's.
        port: [P, 8] flat ports of the projectors (flag column 0 = in air), None = none has one.
        sigma: [3] attenuation of the projected light in the medium (fastneus.train.rig), None = none.
        has_pattern: some frame shows a pattern image (host-side: the renderer asks it every step,
            and asking ``pattern`` would sync with the device).
    """

    K: torch.Tensor
    W: torch.Tensor
    pattern: torch.Tensor
    store: PatternStore
    blur: torch.Tensor | None = None
    port: torch.Tensor | None = None
    sigma: torch.Tensor | None = None
    has_pattern: bool = True
    lights: dict[str, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict)

    @property
    def laser_on(self) -> torch.Tensor | None:
        """[F, P] int32, 1 where projector k is a laser-plane projector lit in frame f (None: no lasers)."""
        return self.lights["laser"][0] if "laser" in self.lights else None

    @property
    def planes(self) -> torch.Tensor | None:
        """[P, L, 12] packed light planes (``fastneus.kernels.project.pack_planes``), None: no lasers."""
        return self.lights["laser"][1] if "laser" in self.lights else None


def pattern_images(scene, frames: list[int], device) -> dict:
    """Pattern id -> [H, W, 3] uint8 image, every pattern ``frames`` show, read once for repeated
    :func:`build_projection` calls (the blur estimate's candidates): numpy on the CPU (OpenCV
    blurs it), a tensor on a GPU (blurred there)."""
    ids = sorted({fp.pattern for i in frames for fp in scene.frames[i].projectors.values() if fp.pattern is not None})
    if torch.device(device).type == "cpu":
        return {p: scene.pattern_image(p) for p in ids}
    return {p: torch.from_numpy(np.ascontiguousarray(scene.pattern_image(p))).to(device) for p in ids}


def build_projection(scene, frames: list[int], device, refraction: bool = True,
                     camera_blur: float = 0.0, patterns: dict | None = None) -> Projection:
    """Collect every projector of ``frames`` (in scene order) into kernel-ready tensors.

    Args:
        scene: the loaded scene; frames: frame indices; device: where the tensors live.
        refraction: keep the projectors' flat ports (underwater housings); False ignores them.
        camera_blur: the camera's blur (Gaussian sigma, camera pixels) applied to the projected
            light: each pattern image is blurred by it in projector pixels
            (:func:`fastneus.train.camblur.projector_scale`); 0 = the patterns as they are.
        patterns: pattern id -> [H, W, 3] uint8 image (numpy, or a tensor on ``device``: blurred
            there) already read (:func:`pattern_images`); others are read from the scene.
    """
    proj_ids = list(scene.projectors.keys())
    S = np.asarray(scene.normalisation(), dtype=np.float64)
    pat_ids: list[str] = []
    F, P = len(frames), max(1, len(proj_ids))
    K = np.zeros((F, P, 3, 3))
    W = np.zeros((F, P, 3, 4))
    pat = -np.ones((F, P), dtype=np.int32)
    kind_of = {pid: get_projector_kind(scene.projectors[pid].kind) for pid in proj_ids}
    # emitters (every kind but the image projector) present, in registration order: their light ops
    emit = [kd.name for kd in projector_kinds() if not kd.images and any(k is kd for k in kind_of.values())]
    on = {name: np.zeros((F, P), dtype=np.int32) for name in emit}
    for a, i in enumerate(frames):
        frame = scene.frames[i]
        for k, pid in enumerate(proj_ids):
            K[a, k] = np.eye(3)
            W[a, k, :, :3] = np.eye(3)
            fp = frame.projectors.get(pid)
            if fp is not None and not kind_of[pid].images and fp.on:
                W[a, k] = (np.asarray(scene.world_to_proj(i, pid), dtype=np.float64) @ S)[:3]
                on[kind_of[pid].name][a, k] = 1
                continue
            if fp is None or fp.pattern is None:
                continue
            K[a, k] = scene.projectors[pid].K
            W[a, k] = (np.asarray(scene.world_to_proj(i, pid), dtype=np.float64) @ S)[:3]
            if fp.pattern not in pat_ids:
                pat_ids.append(fp.pattern)
            pat[a, k] = pat_ids.index(fp.pattern)
    images = [patterns[p] if patterns is not None and p in patterns else scene.pattern_image(p) for p in pat_ids]
    if camera_blur > 0 and pat_ids:  # the lens's blur, moved onto the patterns (fastneus.train.camblur)
        from fastneus.train.camblur import blur_pattern, projector_scale

        scale = {pid: projector_scale(scene, frames, pid) for pid in proj_ids if kind_of[pid].images}
        for q, pid in enumerate(pat_ids):
            users = [scale[proj_ids[k]] for k in range(P) if (pat[:, k] == q).any()]
            images[q] = blur_pattern(images[q], camera_blur * float(np.mean(users)))
    store = PatternStore(images, device) if pat_ids else \
        PatternStore([np.zeros((1, 1, 3), np.uint8)], device)
    t = lambda a, dt=torch.float32: torch.as_tensor(a, dtype=dt, device=device).contiguous()  # noqa: E731
    proj = Projection(t(K), t(W), t(pat, torch.int32), store, has_pattern=bool((pat >= 0).any()))
    for name in emit:
        mine = [scene.projectors[p] if kind_of[p].name == name else None for p in proj_ids]
        if getattr(scene, "grey", False):  # a monochrome camera sees the lasers' light as grey
            from fastneus.light import greyed

            mine = [None if m is None else greyed(m) for m in mine]
        packed = get_projector_kind(name).call("pack", mine, device)
        proj.lights[name] = (t(on[name], torch.int32), packed)
    if refraction and any(scene.projectors[p].port is not None for p in proj_ids):
        rows = [scene.projectors[p].port.row() if scene.projectors[p].port is not None else [0.0] * 8
                for p in proj_ids]
        proj.port = t(np.asarray(rows, dtype=np.float64))
    return proj


class RayBank:
    """All training pixels of a scene as one uint8 store, and the cameras to cast their rays.

    Args:
        scene: a loaded :class:`fastneus.data.Scene`.
        frames: frame indices to use (into ``scene.frames``).
        device: where the store lives (the GPU when training there).
        load_masks: keep masks (uint8) for the mask loss / metrics.
        brightness_cdf: keep a brightness-proportional pixel distribution for ``bright_fraction``.
        background: when given, flag pixels whose every channel is within the tolerance of this
            value in [0, 1] (``self.bg``, [sum HW] bool; ``self.bg_fraction`` their share).
        bg_tolerance, bg_noise_k, bg_cap: the tolerance is :func:`backdrop_tolerance` of these and
            the photos' :func:`backdrop_noise` (``self.bg_tolerance``, ``self.bg_noise``).
        fg_relative: > 0: also flag foreground pixels (``self.fg``, :func:`foreground_flags` with
            the threshold ``bg_cap``); 0: none (the trainer then thresholds each batch).
        refraction: cameras with a flat port (underwater housing) cast refracted rays that start
            on the port's outer face; False treats every camera as a pinhole in one medium.
        lut: [256] decoded (linear) value of each 8-bit code (``fastneus.data.response.decode_lut``):
            ``sample`` returns colours through it, ``mean_rgb`` and background flags use it.
            None = the photos are linear (code / 255).
    """

    def __init__(self, scene, frames: list[int], device, load_masks: bool = False, brightness_cdf: bool = False,
                 background: float | None = None, bg_tolerance: float = 2.0 / 255, refraction: bool = True,
                 lut=None, bg_noise_k: float = 0.0, bg_cap: float = 1.0, fg_relative: float = 0.0):
        self.frames = list(frames)
        self.device = torch.device(device)
        self.lut = None if lut is None else torch.as_tensor(lut, dtype=torch.float32, device=self.device)  # [256]
        sizes, kinv, rot, org, chunks, masks = [], [], [], [], [], []
        for i in self.frames:
            img = scene.image(i)
            h, w = img.shape[:2]
            sizes.append((w, h))
            chunks.append(torch.from_numpy(np.ascontiguousarray(img.reshape(-1, 3))))
            ki, r, o = normalised_camera(scene, i)
            kinv.append(ki)
            rot.append(r)
            org.append(o)
            if load_masks:
                m = scene.mask(i)
                masks.append(None if m is None else torch.from_numpy((np.clip(m, 0, 1) * 255).astype(np.uint8).reshape(-1)))
        self.has_masks = load_masks and all(m is not None for m in masks)
        self.empty_masks = self._empty_masks(scene, masks) if self.has_masks else []
        self.rgb = torch.cat(chunks).to(self.device)                          # [sum HW, 3] uint8
        self.mask = torch.cat(masks).to(self.device) if self.has_masks else None  # [sum HW] uint8
        wh = torch.tensor(sizes, dtype=torch.int64)
        self.wh = wh.to(self.device)                                          # [F, 2]
        self.offset = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(wh[:, 0] * wh[:, 1], 0)[:-1]]).to(self.device)
        f32 = dict(dtype=torch.float32, device=self.device)
        self.kinv = torch.tensor(np.stack(kinv), **f32)                      # [F, 3, 3]
        self.rot = torch.tensor(np.stack(rot), **f32)                        # [F, 3, 3]
        self.origin = torch.tensor(np.stack(org), **f32)                     # [F, 3]
        self.n_pixels = int((wh[:, 0] * wh[:, 1]).sum())
        ports = [scene.frame_camera(i).port for i in self.frames]
        self.port = None                                                     # [F, 8] or None
        if refraction and any(p is not None for p in ports):
            self.port = torch.tensor([p.row() if p is not None else [0.0] * 8 for p in ports], **f32)
            self.radius = float(scene.bounds.radius)
        self.bg, self.bg_fraction = None, 0.0
        self.bg_noise, self.bg_tolerance = 0.0, bg_tolerance
        self._background, self._bg_floor = background, bg_tolerance
        if background is not None:
            self.bg_noise = backdrop_noise(self.rgb, self.lut, background)
            self.bg_tolerance = backdrop_tolerance(bg_tolerance, bg_noise_k, self.bg_noise, bg_cap)
            self.bg = self._bg_flags(background, self.bg_tolerance)             # [sum HW] bool
            self.bg_fraction = float(self.bg.float().mean())
        self.fg = None
        self.bg_soft = None  # [sum HW] uint8 background weight x 255 with the halo (set_halo), or None
        self.mask_core = None  # [sum HW] bool, the masks' core (the trainer sets it: mask_core), or None
        self._fg_load = None  # the foreground flags as read at load while set_fg_halo has trimmed self.fg
        self.fg_halo_share = 0.0  # the share set_fg_halo trimmed self.fg with (0: the flags as loaded)
        self._room = (bg_cap, sizes)  # for lit_room, decided only when asked
        if background is not None and fg_relative > 0:
            self.fg = foreground_flags(self.rgb, self.lut, background, bg_cap, fg_relative, sizes)
        self.cdf = None
        if brightness_cdf:
            # brightness-proportional pixel distribution (float64: millions of pixels)
            w = self.rgb.max(dim=1).values.double() / 255.0 + 1e-3
            self.cdf = torch.cumsum(w, 0)

    @functools.cached_property
    def lit_room(self) -> bool:
        """Whether the photos show a lit room, not lasers in the dark (:func:`lit_room`; the photo
        priors' weight may differ there: ``loss.bg_weight_lit``). False without a background."""
        if self._background is None:
            return False
        return lit_room(self.rgb, self.lut, self._background, *self._room)

    def dark_object(self) -> bool:
        """With masks: whether the object's pixels are mostly dark (median brightest channel,
        linear, under :data:`LIT_ROOM`): lasers in a dark room rather than an ambient-lit object.
        False without masks."""
        if self.mask is None:
            return False
        inside = self.mask > 127
        return bool(inside.any()) and not _bright_objects(_brightness(self.rgb, self.lut, 0.0), inside)

    def _bg_flags(self, background: float, tol: float) -> torch.Tensor:
        """[sum HW] bool: every channel within ``tol`` (linear) of ``background``."""
        if self.lut is not None:  # background and tolerance are linear values
            return background_codes(self.lut, background, tol)[self.rgb.long()].all(dim=1)
        diff = (self.rgb.to(torch.int16) - int(round(255 * background))).abs().amax(dim=1)
        return diff <= int(round(255 * tol))

    def set_halo(self, radius: int, share: float) -> None:
        """Weigh the lens's halo into the background flags (:func:`halo_weights`; batches then carry
        ``bg`` in [0, 1]); radius 0 (a sharp capture) or no foreground flags: the plain flags."""
        self.bg_soft = None
        if radius > 0 and self.bg is not None and self.fg is not None:
            self.bg_soft = halo_weights(self.rgb, self.lut, self._background, self.fg, self.bg, self._room[1],
                                        radius, share)

    def set_fg_halo(self, share: float) -> None:
        """Leave the lens's halo out of the foreground flags (:func:`trim_halo`) with ``share`` > 0,
        or put back the flags read at load with 0. A new tensor either way (a recorded draw graph
        reads the old one: ``graphstep.DRAW_FIELDS``); nothing when ``share`` is the one in use."""
        if self.fg is None or self.bg is None or share == self.fg_halo_share:
            return
        self.fg_halo_share = share
        if self._fg_load is None:
            self._fg_load = self.fg
        self.fg = self._fg_load.clone() if share <= 0 else trim_halo(
            self._fg_load, self.bg, _brightness(self.rgb, self.lut, self._background), self._room[1], share)

    def use_floor_background(self) -> None:
        """Flag background with the fixed tolerance (outside a dark room the wider, noise-floor
        tolerance carves dim, ambient-lit surface: realistic rock Dark 9.0 -> 12.7 mm)."""
        if self.bg is not None and self.bg_tolerance > self._bg_floor:
            self.bg_tolerance = self._bg_floor
            self.bg = self._bg_flags(self._background, self.bg_tolerance)
            self.bg_soft = None  # weights made from the old flags would be stale: set_halo again

    def _empty_masks(self, scene, masks: list) -> list[str]:
        """Mask files that are all zero. All of them empty is an error (nothing to reconstruct:
        a wrong folder or an inverted export); some empty is allowed (the object can leave a view).

        Returns:
            The empty masks' paths, for a warning.
        """
        empty = [a for a, m in enumerate(masks) if not bool(m.any())]
        if empty and len(empty) == len(masks):
            i = self.frames[0]
            raise FastneusError("mask is empty (all zero), and so is every other training mask: no pixel "
                                "shows the object", file=scene.path(scene.frames[i].mask), field=f"frames[{i}].mask")
        return [str(scene.path(scene.frames[self.frames[a]].mask)) for a in empty]

    def mean_rgb(self, chunk: int = 1 << 22) -> torch.Tensor:
        """[3] mean pixel colour in [0, 1] (linear), summed in chunks (no float copy of the whole store)."""
        if self.lut is not None:  # through the response: per-channel code histograms
            hist = torch.stack([torch.bincount(self.rgb[:, c].long(), minlength=256) for c in range(3)]).cpu()
            return lut_mean(hist, self.lut, self.n_pixels).to(self.device)
        tot = torch.zeros(3, dtype=torch.float64, device=self.device)
        for a in range(0, self.n_pixels, chunk):
            tot += self.rgb[a:a + chunk].sum(0, dtype=torch.float64)
        return (tot / (255.0 * max(1, self.n_pixels))).float()

    def store_bytes(self) -> int:
        """Bytes of the image store."""
        return self.rgb.numel() * self.rgb.element_size()

    def rays(self, fidx: torch.Tensor, u: torch.Tensor, v: torch.Tensor):
        """Rays through pixel centres.

        Args:
            fidx: [B] int64 index into ``self.frames``; u, v: [B] float32 continuous pixel coords
                (pixel centre of integer pixel (c, r) is (c + 0.5, r + 0.5)).
        Returns:
            origins [B, 3], dirs [B, 3] (unit) in normalised space.
        """
        pix = torch.stack([u, v, torch.ones_like(u)], -1)
        d_cam = torch.einsum("bij,bj->bi", self.kinv[fidx], pix)
        if self.port is not None:  # underwater: refract at the flat port, start in the water
            return self._refracted(fidx, d_cam / d_cam.norm(dim=-1, keepdim=True))
        d = torch.einsum("bij,bj->bi", self.rot[fidx], d_cam)
        d = d / d.norm(dim=-1, keepdim=True)
        return self.origin[fidx].contiguous(), d.contiguous()

    def _refracted(self, fidx: torch.Tensor, d_cam: torch.Tensor):
        from fastneus.geometry.projection import refract_rays

        o = self.origin[fidx].clone()
        d = torch.einsum("bij,bj->bi", self.rot[fidx], d_cam)
        for f in torch.unique(fidx).tolist():
            row = self.port[f]
            if float(row[7]) == 0.0:
                continue
            sel = fidx == f
            b, w = refract_rays(d_cam[sel], row)
            R = self.rot[f]
            o[sel] = o[sel] + (b @ R.T) / self.radius
            d[sel] = w @ R.T
        return o.contiguous(), (d / d.norm(dim=-1, keepdim=True)).contiguous()

    def sample(self, n: int, generator: torch.Generator | None = None, bright_fraction: float = 0.0,
               blur: float = 0.0, sub: int = 1):
        """``n`` random (frame, pixel) pairs: uniform over all pixels of all frames, except a
        ``bright_fraction`` share drawn in proportion to pixel brightness (needs ``brightness_cdf``).

        With ``blur`` > 0 each pixel is ``sub`` rays through points spread around its centre by
        a Gaussian of ``blur`` pixels (the camera's defocus: the caller averages their colours,
        so the model is compared with the photo as the blurred lens formed it).

        Returns:
            dict: fidx [n * sub] int32, origins [n * sub, 3], dirs [n * sub, 3] (pixel-major: the
            rays of pixel i are rows i*sub .. i*sub+sub-1), rgb [n, 3] float in [0, 1] (linear:
            through ``lut``), sat [n, 3] bool (the photo's channel is >= :data:`SATURATED`),
            mask [n] float (if masks), bg [n] float 1/0 (if ``background`` was given),
            pix [n] int64 flat pixel index.
        """
        flat, fidx, col, row = draw_pixels(self, n, generator, bright_fraction)
        u, v = col.float() + 0.5, row.float() + 0.5
        if blur > 0 and sub > 1:
            # a quadrature of the Gaussian, not random draws: sub points on a circle of radius
            # blur * sqrt(2) (the Gaussian's second moment), turned at random per pixel; random
            # offsets left the mean of a few rays too noisy across a 1-2 px laser line
            a = torch.rand(n, 1, device=self.device, generator=generator) * (2 * math.pi / sub) \
                + torch.arange(sub, device=self.device) * (2 * math.pi / sub)         # [n, sub]
            r = blur * math.sqrt(2.0)
            u = (u[:, None] + r * torch.cos(a)).reshape(-1)
            v = (v[:, None] + r * torch.sin(a)).reshape(-1)
            fidx = fidx.repeat_interleave(sub)
        o, d = self.rays(fidx, u, v)
        return {"fidx": fidx.to(torch.int32), "origins": o, "dirs": d, **pixel_fields(self, flat, self.rgb[flat])}

    def image_rays(self, a: int):
        """All rays of frame ``self.frames[a]`` in row-major order: (origins, dirs, (h, w))."""
        w, h = (int(x) for x in self.wh[a].tolist())
        row, col = torch.meshgrid(torch.arange(h, device=self.device), torch.arange(w, device=self.device), indexing="ij")
        fidx = torch.full((h * w,), a, dtype=torch.int64, device=self.device)
        o, d = self.rays(fidx, col.reshape(-1).float() + 0.5, row.reshape(-1).float() + 0.5)
        return o, d, (h, w)

    def image(self, a: int) -> torch.Tensor:
        """[H, W, 3] uint8 of frame ``self.frames[a]``."""
        w, h = (int(x) for x in self.wh[a].tolist())
        off = int(self.offset[a])
        return self.rgb[off:off + w * h].reshape(h, w, 3)


def to_linear(u8: torch.Tensor, lut: torch.Tensor | None) -> torch.Tensor:
    """uint8 photo values (any shape) -> float linear values: ``lut[u8]``, or ``u8 / 255`` without one."""
    return u8.float() / 255.0 if lut is None else lut[u8.long()]


def core_radius(frac: float, w: int, h: int) -> int:
    """The erosion radius in pixels for ``loss.mask_core`` (a fraction of the image's larger side,
    at least 1 px): the band where a pixel-centre ray may only graze the surface widens with the
    resolution (NeuS's soft surface spans more pixels), so the radius scales with the image."""
    return max(1, int(round(frac * max(w, h))))


def mask_core(mask: torch.Tensor, wh: torch.Tensor, frac: float, thin: bool = False) -> torch.Tensor:
    """The mask's core: mask pixels whose (2 r + 1)-square neighbourhood is all mask, r =
    :func:`core_radius` per frame (an erosion; the image border does not erode). A ray through the
    core crosses the object well inside its outline, where full opacity is what the photo says; a
    ray on the rim may only graze it.

    With ``thin``, also the mask's parts narrower than the square (the mask minus its opening, the
    eroded mask dilated back): a leg or an antenna has no core and no grazing rim beside one, only
    rays that cross it; the SDF hinge stops pulling once such a ray enters it and lets a defocused
    photo thin it, which the opacity does not.

    Args:
        mask: [sum HW] uint8 masks of the frames, concatenated (x 255); wh: [F, 2] (width, height);
        frac: the radius as a fraction of each frame's larger side (> 0); thin: add the thin parts.
    Returns:
        [sum HW] bool on the masks' device.
    """
    import cv2

    # OpenCV's rectangle morphology costs O(1) per pixel whatever the radius (a torch max-pool costs
    # O(r^2): 12 s for one 3-Mpx photo at r = 40 on a CPU); its default border neither erodes nor dilates
    inside = (mask > 127).to(torch.uint8).cpu().numpy()
    out, off = [], 0
    for w, h in wh.tolist():
        px = core_radius(frac, w, h)
        square = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * px + 1, 2 * px + 1))
        m = inside[off:off + w * h].reshape(h, w)
        core = cv2.erode(m, square)
        if thin:  # mask - opening(mask): the opening lies inside the mask, so no uint8 wrap
            core = np.maximum(core, m - cv2.dilate(core, square))
        out.append(core.reshape(-1))
        off += w * h
    return torch.from_numpy(np.concatenate(out)).to(mask.device) > 0


def pixel_fields(bank, flat: torch.Tensor, u8: torch.Tensor) -> dict:
    """What a batch carries per drawn pixel: its photo values (linear through ``bank.lut``), the
    saturated channels, the flat index, and the mask and background flag when the bank has them.

    Args:
        bank: a RayBank or ShotBank (``lut``, ``mask``, ``bg``).
        flat: [n] int64 flat pixel indices; u8: [n, ..., 3] uint8 photo values of those pixels.
    """
    out = {"rgb": to_linear(u8, bank.lut), "sat": u8 >= SATURATED, "pix": flat}
    if bank.mask is not None:
        out["mask"] = bank.mask[flat].float() / 255.0
        core = getattr(bank, "mask_core", None)  # the masks' core (loss.mask_core), or None
        if core is not None:
            out["core"] = core[flat].float()
    soft = getattr(bank, "bg_soft", None)  # the lens's halo weighted in (RayBank.set_halo)
    if soft is not None:
        out["bg"] = soft[flat].float() / 255.0
    elif bank.bg is not None:
        out["bg"] = bank.bg[flat].float()
    if getattr(bank, "fg", None) is not None:
        out["fg"] = bank.fg[flat].float()
    return out


def draw_pixels(bank, n: int, generator: torch.Generator | None, bright_fraction: float):
    """``n`` flat pixel indices of ``bank`` (uniform, except a ``bright_fraction`` share drawn in
    proportion to brightness when ``bank.cdf`` exists) and their image, column and row.

    ``bank`` has ``n_pixels``, ``cdf`` ([N] float64 or None), ``offset`` ([I+1] first pixel of
    each image), ``wh`` ([I, 2]) and ``device`` (a RayBank: images = frames; a ShotBank: views).

    Returns:
        flat [n] int64, image [n] int64, col [n] int64, row [n] int64.
    """
    flat = torch.randint(0, bank.n_pixels, (n,), device=bank.device, generator=generator)
    nb = int(n * bright_fraction) if bank.cdf is not None else 0
    if nb > 0:
        r = torch.rand(nb, device=bank.device, generator=generator, dtype=torch.float64) * bank.cdf[-1]
        flat[:nb] = torch.searchsorted(bank.cdf, r).clamp_max(bank.n_pixels - 1)
    image = torch.searchsorted(bank.offset, flat, right=True) - 1
    local = flat - bank.offset[image]
    w = bank.wh[image, 0]
    return flat, image, local % w, local // w
