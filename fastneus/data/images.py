"""Image files of a scene: header parsing (PNG without decoding), EXIF orientation, the checks of
size, channels and bit depth, reading photos, masks and patterns, and lens undistortion."""
from __future__ import annotations

import math
import os
import struct
import sys
from pathlib import Path

import numpy as np

from fastneus.data.validate import field_error

MAX_PIXELS = 1 << 30  # OpenCV's CV_IO_MAX_IMAGE_PIXELS: imread refuses larger images

# PNG colour type -> channels as decoded (palette images decode to colour)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}


def image_info(path: str | os.PathLike) -> tuple[int, int, int, int] | None:
    """(width, height, channels, bits per channel) of an image; None if unreadable.

    PNG is read from its header only; other formats are decoded once.
    """
    path = str(path)
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return None
    if len(head) >= 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        bits = 8 if head[25] == 3 else int(head[24])  # palette: 8-bit colours whatever the index size
        return int(w), int(h), _PNG_CHANNELS.get(head[25], 0), bits
    import cv2  # on first use: the CLI does not pay for OpenCV at start-up

    try:
        im = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    except cv2.error:  # a header OpenCV refuses (e.g. more pixels than it decodes)
        return None
    if im is None:
        return None
    return int(im.shape[1]), int(im.shape[0]), 1 if im.ndim == 2 else int(im.shape[2]), 8 * im.dtype.itemsize


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) of an image, reading only the header for PNG; None if unreadable."""
    info = image_info(path)
    return None if info is None else info[:2]


# what each kind of image may be (channels, bits): photos are 8- or 16-bit colour or grey (a 16-bit
# set is linearised and kept as 8-bit sRGB codes: Scene.image; a grey one comes as three equal
# channels and the projectors' light is made grey to match: Scene.grey); masks use channel 0 (8 or
# 16 bit); patterns may be grey (white light). Alpha is never dropped silently.
_IMAGE_KINDS = {"image": ((1, 3), (8, 16)), "mask": ((1, 3), (8, 16)), "pattern": ((1, 3), (8,))}


def check_image(root: Path, rel: str, size: tuple[int, int] | None, file, fld: str,
                kind: str = "image") -> tuple[int, int]:
    """Check that image ``rel`` exists, is readable, has ``size`` and what ``kind`` may have; returns
    its (bits per channel, channels). Raises a FastneusError naming ``file`` and ``fld`` otherwise."""
    p = root / rel
    if not p.is_file():
        raise field_error(f"file not found: {p}", file, fld)
    info = image_info(p)
    if info is None:
        raise field_error(f"cannot read image {p}", file, fld)
    w, h, ch, bits = info
    if size is not None and (w, h) != tuple(size):
        raise field_error(f"image {rel} is {w}x{h} but should be {size[0]}x{size[1]}", file, fld)
    channels, depths = _IMAGE_KINDS[kind]
    if ch in (2, 4):
        raise field_error(f"{kind} {rel} has an alpha channel, which fastneus would drop; save it without alpha "
                          f"(a transparent background belongs in a mask)", file, fld)
    if ch not in channels:
        raise field_error(f"{kind} {rel} has {ch} channel(s); expected {' or '.join(map(str, channels))}", file, fld)
    if bits not in depths:
        raise field_error(f"{kind} {rel} is {bits}-bit; expected {' or '.join(map(str, depths))}-bit per channel",
                          file, fld)
    if w * h > MAX_PIXELS:  # only a PNG header is read here; OpenCV refuses to decode more
        raise field_error(f"{kind} {rel} is {w}x{h}, more than the {MAX_PIXELS} pixels OpenCV decodes", file, fld)
    warn_orientation(p)
    return bits, ch


def _exif_orientation_tiff(tiff: bytes) -> int | None:
    """The Orientation tag (0x0112) of IFD0 in a TIFF-structured EXIF block, None if absent or malformed."""
    if len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return None
    e = "<" if tiff[:2] == b"II" else ">"
    ifd = struct.unpack(e + "I", tiff[4:8])[0]
    if ifd + 2 > len(tiff):
        return None
    n = struct.unpack(e + "H", tiff[ifd:ifd + 2])[0]
    for k in range(min(n, 512)):
        at = ifd + 2 + 12 * k
        if at + 12 > len(tiff):
            return None
        tag, typ = struct.unpack(e + "HH", tiff[at:at + 4])
        if tag == 0x0112 and typ == 3:  # SHORT, stored in the first 2 bytes of the value field
            return struct.unpack(e + "H", tiff[at + 8:at + 10])[0]
    return None


def exif_orientation(path: str | os.PathLike) -> int | None:
    """The EXIF Orientation of a JPEG (APP1 ``Exif``) or PNG (``eXIf`` chunk), read from the
    file's first 256 KB without decoding pixels; None when there is none."""
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 18)
    except OSError:
        return None
    try:
        if head[:2] == b"\xff\xd8":  # JPEG: walk the marker segments before the image data
            at = 2
            while at + 4 <= len(head) and head[at] == 0xFF:
                marker, size = head[at + 1], struct.unpack(">H", head[at + 2:at + 4])[0]
                if marker == 0xE1 and head[at + 4:at + 10] == b"Exif\x00\x00":
                    return _exif_orientation_tiff(head[at + 10:at + 2 + size])
                if marker in (0xD9, 0xDA) or size < 2:  # end of image / start of scan
                    return None
                at += 2 + size
        elif head[:8] == b"\x89PNG\r\n\x1a\n":
            at = 8
            while at + 8 <= len(head):
                size, kind = struct.unpack(">I4s", head[at:at + 8])
                if kind == b"eXIf":
                    return _exif_orientation_tiff(head[at + 8:at + 8 + size])
                if kind in (b"IDAT", b"IEND"):
                    return None
                at += 12 + size
    except struct.error:
        return None
    return None


_ORIENTATION_WARNED: set[str] = set()


def warn_orientation(path: str | os.PathLike) -> None:
    """One stderr line (once per file) when an image carries an EXIF rotation/flip that fastneus ignores."""
    o = exif_orientation(path)
    if o not in (None, 1) and str(path) not in _ORIENTATION_WARNED:
        _ORIENTATION_WARNED.add(str(path))
        print(f"warning: {path}: EXIF orientation {o} ignored; fastneus uses the pixels as stored, which the "
              "intrinsics and masks must describe (re-save the file without the tag if it is wrong)",
              file=sys.stderr)


def imread(path: Path, flags: int, file, fld: str) -> np.ndarray:
    """``cv2.imread`` with ``flags`` and the EXIF orientation ignored (pixels as stored, like the
    size check and the masks), one-line errors; None never escapes."""
    import cv2  # on first use: the CLI does not pay for OpenCV at start-up

    if flags != cv2.IMREAD_UNCHANGED:  # IMREAD_UNCHANGED ignores the orientation already (and is -1)
        flags |= cv2.IMREAD_IGNORE_ORIENTATION
    try:
        im = cv2.imread(str(path), flags)
    except cv2.error as e:  # e.g. a header claiming more pixels than OpenCV decodes
        raise field_error(f"cannot read image {path}: {str(e).strip().splitlines()[-1][:200]}", file, fld) from None
    if im is None:
        raise field_error(f"cannot read image {path}", file, fld)
    return im


def read_rgb(path: Path, file, fld: str, deep: bool = False) -> np.ndarray:
    """RGB [H, W, 3]: uint8, or with ``deep`` the file's own depth (uint16 for a 16-bit file)."""
    import cv2  # on first use: the CLI does not pay for OpenCV at start-up

    im = imread(path, (cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH) if deep else cv2.IMREAD_COLOR, file, fld)
    return np.ascontiguousarray(im[:, :, ::-1])


def read_mask(path: Path, file, fld: str) -> np.ndarray:
    """float32 [H, W] in [0, 1] from channel 0 of an 8- or 16-bit mask (soft edges kept)."""
    import cv2  # on first use: the CLI does not pay for OpenCV at start-up

    m = imread(path, cv2.IMREAD_UNCHANGED, file, fld)
    if m.ndim == 3:
        m = m[:, :, 0]
    scale = 65535.0 if m.dtype == np.uint16 else 255.0
    return m.astype(np.float32) / scale


def undistort(im: np.ndarray, K: np.ndarray, dist: np.ndarray, nearest: bool = False) -> np.ndarray:
    """``im`` with the lens distortion ``dist`` (k1 k2 p1 p2 k3) of a camera with intrinsics ``K`` removed;
    ``im`` itself when there is none."""
    if not np.any(dist):
        return im
    import cv2  # on first use: the CLI does not pay for OpenCV at start-up

    # cv2 uses the pixel-corner convention for integer coords; shift K by half a pixel
    K = K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    if nearest:
        m1, m2 = cv2.initUndistortRectifyMap(K, dist, None, K, (im.shape[1], im.shape[0]), cv2.CV_32FC1)
        return cv2.remap(im, m1, m2, cv2.INTER_NEAREST)
    return cv2.undistort(im, K, dist)


def gaussian_blur(img, sigma: float, border: str = "zeros"):
    """``img`` [H, W, C] float tensor blurred by a separable Gaussian of ``sigma`` pixels (taps out to
    ceil(3 sigma), normalised; OpenCV's kernel of that size), same device and dtype.

    Args:
        img: [H, W, C] float tensor. sigma: > 0, pixels.
        border: ``zeros`` (nothing outside the image: a pattern's dark surround) or ``replicate``
            (the edge pixels continue: a photo's border).
    """
    import torch  # noqa: PLC0415 (the CLI reads image headers without paying for torch)

    r = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=img.dtype, device=img.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    t = img.permute(2, 0, 1)[:, None]  # [C, 1, H, W]
    t = torch.nn.functional.pad(t, (r, r, r, r), mode="replicate" if border == "replicate" else "constant")
    t = torch.nn.functional.conv2d(t, k.view(1, 1, 1, -1))
    t = torch.nn.functional.conv2d(t, k.view(1, 1, -1, 1))
    return t[:, 0].permute(1, 2, 0)
