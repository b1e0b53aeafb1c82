"""fastneus.light: what projectors emit: pattern generators and decoders, laser planes; and that
light as a monochrome camera sees it (:func:`grey_rgb`, :func:`greyed`)."""
from __future__ import annotations

import dataclasses

import numpy as np


def grey_rgb(im: np.ndarray) -> np.ndarray:
    """[..., 3] RGB -> the same shape with each pixel's channel mean in all three channels.

    What a monochrome camera records of coloured light is the light's sum weighted by the
    sensor's spectral sensitivity, which no file states: the plain mean keeps white light as it
    is, and the learned i_r absorbs the sensor's sensitivity to a one-colour projector (a red
    laser reads as 1/3 of white here; i_r then comes out 3x the sensor's relative response).
    uint8 in, uint8 out (rounded); floats stay floats.
    """
    m = np.asarray(im).astype(np.float64).mean(axis=-1, keepdims=True)
    if np.asarray(im).dtype == np.uint8:
        m = np.clip(np.round(m), 0, 255).astype(np.uint8)
    else:
        m = m.astype(np.asarray(im).dtype)
    return np.ascontiguousarray(np.broadcast_to(m, np.shape(im)))


def greyed(projector):
    """A projector whose laser planes' colours are grey (:func:`grey_rgb`); others as they are
    (a pattern projector's images are made grey where they are read: ``Scene.pattern_image``)."""
    planes = getattr(projector, "planes", None)
    if not planes:
        return projector
    grey = [dataclasses.replace(pl, colour=grey_rgb(np.asarray(pl.colour, dtype=np.float64))) for pl in planes]
    return dataclasses.replace(projector, planes=grey)
