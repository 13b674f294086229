"""One image's edges in every form the stages after edge detection need."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import Camera
from ..params import EdgeParams
from .image_edges import ImageEdges, edge_pixels, finished_without_background, line_segments, refinement_params
from .scoring import EdgeEvidence
from .workers import SERIAL, WorkerPool


@dataclass
class Frame:
    """The image's line segments in pixels and undistorted, its edge pixels prepared for
    scoring (``evidence``) and undistorted too, and the camera that took it."""

    segments_px: np.ndarray  # (N, 2, 2)
    segments_n: np.ndarray  # (N, 2, 2) normalised camera coordinates
    refine_segments_n: np.ndarray  # (M, 2, 2) the pose refinement's segments, normalised
    camera: Camera
    evidence: EdgeEvidence
    edge_points_n: np.ndarray  # evidence.pixels in normalised camera coordinates
    #: the bounding-box diagonals (pixels) of the connected regions of ``detect``'s ``mask``,
    #: the only places the part can lie (its colour regions); None: the whole image
    region_extents: np.ndarray | None = None
    #: the image's grey levels (``image_edges.to_gray``), which the shading fit reads
    #: (``appearance.shading_fit``); None: not kept
    gray: np.ndarray | None = None

    @classmethod
    def of(cls, edges: ImageEdges, camera: Camera) -> "Frame":
        return cls._with(edges, camera, _evidence(edges))

    @classmethod
    def detect(cls, image: np.ndarray, camera: Camera, params: EdgeParams, pool: WorkerPool = SERIAL,
               tolerances: tuple[float, ...] = (), mask: np.ndarray | None = None) -> tuple[ImageEdges, "Frame"]:
        """``detect_edges`` and ``of`` at once: after Canny, the line segments (Hough, merge,
        refit) and the evidence for scoring, which both start from the edge pixels alone,
        run on the ``pool``'s threads, the evidence's maps one job per direction bin
        (``EdgeEvidence.bin_jobs``): its nearest-edge table (``EdgeEvidence.nearest_like``,
        which every image with a pose aligns on, its polish at least) and its maps at the
        score's ``tolerances``, pixels (``scoring.scored_tolerances``), all built once per
        image before the refinement's threads would each wait for them. ``mask`` (H, W) bool
        keeps only its edge pixels (one part's ``colour_regions``), and its regions' sizes
        (``region_extents``) bound the template search's; Canny's thresholds are the whole
        image's either way. Edge pixels along lines too long to be a part's are dropped
        (``image_edges.without_background``), as ``detect_edges`` drops them."""
        pixels = edge_pixels(image, params)
        if mask is not None:
            pixels = dataclasses.replace(pixels, edge_map=np.where(mask, pixels.edge_map, 0).astype(np.uint8))

        def segments_and_evidence(pixels: ImageEdges) -> tuple:
            evidence = _evidence(pixels)
            segments, refine_segments, *nearest = pool.map(lambda job: job(), [
                lambda: line_segments(pixels, params), lambda: line_segments(pixels, refinement_params(params)),
                *evidence.bin_jobs(tolerances)])
            return segments, refine_segments, evidence, nearest

        pixels, (segments, refine_segments, evidence, nearest) = finished_without_background(
            pixels, params, segments_and_evidence)
        evidence.adopt(nearest)
        edges = dataclasses.replace(pixels, segments=segments, refine_segments=refine_segments)
        return edges, cls._with(edges, camera, evidence, None if mask is None else region_extents(mask))

    @classmethod
    def warm_up(cls, params: EdgeParams, pool: WorkerPool, tolerances: tuple[float, ...]) -> None:
        """``detect`` once on a drawn 640 x 480 image (a lighter rectangle on grey): OpenCV's
        and numpy's first calls at a camera image's size, and the ``pool``'s threads, cost the
        first image about 10 ms of edges otherwise, a third of a clean image (at most 2x the
        steady state is the node's target; docs/results/latency.md)."""
        image = np.full((480, 640), 60, np.uint8)
        image[120:360, 160:480] = 200
        cls.detect(image, Camera(500.0, 500.0, 320.0, 240.0, 640, 480), params, pool, tolerances)

    @classmethod
    def _with(cls, edges: ImageEdges, camera: Camera, evidence: EdgeEvidence,
              region_extents: np.ndarray | None = None) -> "Frame":
        return cls(segments_px=edges.segments, segments_n=camera.undistort(edges.segments),
                   refine_segments_n=camera.undistort(edges.refine_segments), camera=camera,
                   evidence=evidence, edge_points_n=camera.undistort(evidence.pixels), region_extents=region_extents,
                   gray=edges.gray)


def region_extents(mask: np.ndarray) -> np.ndarray:
    """The bounding-box diagonals (pixels) of the 8-connected regions of a bool mask (H, W)."""
    count, _, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return np.hypot(stats[1:count, cv2.CC_STAT_WIDTH], stats[1:count, cv2.CC_STAT_HEIGHT]).astype(np.float64)


def _evidence(edges: ImageEdges) -> EdgeEvidence:
    return EdgeEvidence(edges.edge_map, edges.gradient_x, edges.gradient_y)
