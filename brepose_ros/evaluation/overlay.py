"""Debug drawing of one estimate over its image (no ROS): the node's ``~/debug_image``
and the evaluation plots use the same picture, so what a user sees live is what a report shows.

Model edges (projected with the final pose) are green when the part was found and red when
it was not; the image edges they were matched to are thin yellow. A caption gives the score,
error ratio and chosen view.
"""
from __future__ import annotations

import cv2
import numpy as np

from ..online.estimator import Estimate

FOUND = (0, 220, 0)
NOT_FOUND = (0, 0, 255)
IMAGE_EDGE = (0, 230, 255)
#: cv2 draws with fixed-point coordinates: 4 fractional bits keep sub-pixel end points
_SHIFT = 4


def to_bgr8(image: np.ndarray) -> np.ndarray:
    """A displayable 8-bit BGR copy of a gray, BGR or BGRA uint8/uint16 image.

    16-bit images are stretched to their own maximum: raw 12-bit cameras store values far
    below 65535 and would otherwise look black.
    """
    image = np.asarray(image)
    if image.dtype == np.uint16:
        peak = int(image.max()) if image.size else 0
        image = cv2.convertScaleAbs(image, alpha=255.0 / peak if peak else 1.0)
    elif image.dtype != np.uint8:
        raise ValueError(f"overlay needs a uint8 or uint16 image, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.ndim == 3 and image.shape[2] == 3:
        return image.copy()
    raise ValueError(f"overlay needs a gray, BGR or BGRA image, got shape {image.shape}")


def draw_segments(canvas: np.ndarray, segments: np.ndarray, color, thickness: int) -> None:
    """Draw (K, 2, 2) pixel segments in place, anti-aliased and at sub-pixel precision."""
    fixed = np.round(np.asarray(segments, dtype=float).reshape(-1, 2, 2) * (1 << _SHIFT)).astype(np.int64)
    for (x0, y0), (x1, y1) in fixed:
        cv2.line(canvas, (int(x0), int(y0)), (int(x1), int(y1)), color, thickness, cv2.LINE_AA, _SHIFT)


def caption(estimate: Estimate, label: str = "") -> str:
    state = "found" if estimate.found else "not found"
    text = (f"{state}  score {estimate.score:.2f}  confidence {estimate.confidence:.2f}"
            f"  error ratio {estimate.error_ratio:.2f}"
            f"  view {estimate.view_index}  edges {estimate.n_image_segments}"
            f"  matched {estimate.n_matched}")
    if estimate.ambiguous:  # the image cannot tell the pose from a symmetric twin
        text += f"  ambiguous (twin margin {estimate.symmetry_margin:.2f})"
    return f"{label}: {text}" if label else text


def draw_overlay(image: np.ndarray, estimate: Estimate, label: str = "") -> np.ndarray:
    """BGR uint8 picture of ``image`` with the estimate's matched edges and a caption."""
    canvas = to_bgr8(image)
    height, width = canvas.shape[:2]
    thickness = max(1, round(np.hypot(width, height) / 700))
    draw_segments(canvas, estimate.image_segments, IMAGE_EDGE, thickness)
    draw_segments(canvas, estimate.model_segments, FOUND if estimate.found else NOT_FOUND, thickness + 1)
    scale = max(0.4, width / 1600)
    text = caption(estimate, label)
    (text_w, text_h), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.rectangle(canvas, (0, 0), (min(width, text_w + 8), text_h + baseline + 8), (0, 0, 0), cv2.FILLED)
    cv2.putText(canvas, text, (4, text_h + 4), cv2.FONT_HERSHEY_SIMPLEX, scale,
                FOUND if estimate.found else NOT_FOUND, 1, cv2.LINE_AA)
    return canvas
