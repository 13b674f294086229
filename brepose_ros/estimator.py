"""The online pipeline behind one call: image + intrinsics in, metric 6-DoF pose out."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Estimate:
    """What the estimator found in one image (CONVENTIONS.md pose and metrics).

    ``R``/``t`` are T_cam_model (metres) or None when the part was not found. ``score`` in
    [0, 1] is the share of the projected visible model edges that an image edge confirms;
    ``error_ratio`` the share of the chosen view's matched model edges outside the nearest
    group (0 best, 1 worst).
    """

    found: bool
    R: np.ndarray | None
    t: np.ndarray | None
    score: float
    error_ratio: float
    view_index: int
    n_image_segments: int
    n_matched: int
    n_nearest: int
    #: matched pairs for overlays: image segments and the model segments projected with
    #: the final pose, both (K, 2, 2) in pixels
    image_segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    model_segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    timings: dict[str, float] = field(default_factory=dict)
