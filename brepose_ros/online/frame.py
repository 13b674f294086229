"""One image's edges in every form the stages after edge detection need."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from .image_edges import ImageEdges
from .scoring import EdgeEvidence


@dataclass
class Frame:
    """The image's line segments in pixels and undistorted, its edge pixels prepared for
    scoring (``evidence``) and undistorted too, and the camera that took it."""

    segments_px: np.ndarray  # (N, 2, 2)
    segments_n: np.ndarray  # (N, 2, 2) normalised camera coordinates
    camera: Camera
    evidence: EdgeEvidence
    edge_points_n: np.ndarray  # evidence.pixels in normalised camera coordinates

    @classmethod
    def of(cls, edges: ImageEdges, camera: Camera) -> "Frame":
        evidence = EdgeEvidence(edges.edge_map, edges.gradient_x, edges.gradient_y)
        return cls(segments_px=edges.segments, segments_n=camera.undistort(edges.segments), camera=camera,
                   evidence=evidence, edge_points_n=camera.undistort(evidence.pixels))
