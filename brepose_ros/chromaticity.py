"""A surface's or an image's colour as a chromaticity histogram: what a scanned mesh's
colour is compiled into (``offline.mesh``), stored as (``aspect_graph``) and compared with
in a colour image (``online.colour_regions``).

Chromaticity (r, g) = (R, G) / (R + G + B) is what a brighter or dimmer light leaves alone;
it is counted in ``BINS`` x ``BINS`` bins.
"""
from __future__ import annotations

import cv2
import numpy as np

#: chromaticity bins along r and along g
BINS = 32


def surface_histogram(colours_bgr: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The model's colour: (BINS, BINS) float32 chromaticity histogram summing to 1 of
    surface colours (N, 3) uint8 BGR weighted by the surface area each stands for (N,),
    smoothed over a bin so that a slightly different light still finds it."""
    r, g = chromaticity_bins(colours_bgr)
    return smoothed(histogram(r, g, np.asarray(weights, np.float32)))


def chromaticity_bins(bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (r, g) bins of BGR uint8 colours (..., 3), each shaped as the colours' leading axes;
    one is added to every channel so that black has a chromaticity (grey's)."""
    values = bgr.astype(np.float32) + 1.0
    total = values.sum(axis=-1)
    r = np.minimum((values[..., 2] / total * BINS).astype(np.intp), BINS - 1)
    g = np.minimum((values[..., 1] / total * BINS).astype(np.intp), BINS - 1)
    return r, g


def histogram(r: np.ndarray, g: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(BINS, BINS) float32 counts (or summed weights) of the bins (r, g)."""
    flat = np.bincount((r * BINS + g).ravel(), weights, minlength=BINS * BINS)
    return flat.reshape(BINS, BINS).astype(np.float32)


def smoothed(histogram: np.ndarray) -> np.ndarray:
    """A histogram blurred over one bin either way and scaled to sum 1."""
    blurred = cv2.GaussianBlur(histogram, (3, 3), 0)
    return blurred / max(float(blurred.sum()), 1e-12)
