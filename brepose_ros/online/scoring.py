"""Verification: how well a pose's projected model edges and the image's edge pixels
explain each other beyond chance (the score), and the seed paper's error ratio at the
final pose.

The score is what every stage after matching compares: hypotheses of all generators, the
steps of the view climb, the polish, the twin check, and the found / not-found decision.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from functools import cached_property, lru_cache, partial
from typing import TYPE_CHECKING, Callable, NamedTuple

import cv2
import numpy as np

from ..aspect_graph import AspectGraph
from ..offline.hidden_lines import SHARP
from ..camera import Camera, project_normalised
from ..params import EstimatorParams, PoseParams
from .kernels import pose_evidence_kernel, run_on_kernel
from .kernels import grown_outline
from .lines2d import nearest_lines, samples_along
from .workers import SERIAL, WorkerPool

if TYPE_CHECKING:
    from .frame import Frame

#: how far (in units of pose.inlier_pixels) a model edge may lie from an image line and
#: still count as matched for the error ratio, the pose's residual error and the line
#: detector's included; within 1 unit it is in the nearest group
ERROR_RATIO_REACH = 4.0

#: a pose scoring this high is not searched further (not climbed, no other start climbed
#: after it, no clusters matched once the whole image holds it): on the bench images no
#: other start or cluster beat such a pose, and climbing it only chased the score's pixel
#: noise (docs/DECISIONS.md)
CLEAR_SCORE = 0.95


def pose_scores(graph: AspectGraph, R: np.ndarray, t: np.ndarray, frame: "Frame", p: PoseParams) -> np.ndarray:
    """For B poses (B, 3, 3), (B, 3): ``Shares.score`` of ``EdgeEvidence.shares`` on the
    image's edge pixels, 0 for a pose behind the camera or projecting smaller than
    ``pose.min_size_pixels`` (a part that small is not recognisable, and a tiny pose fits
    any edges).

    Of the projected visible model edges, the share an image edge confirms beyond what
    chance would (occlusion lowers it by what it hides, clutter does not raise it); of the
    image edges inside the projected part's outline where the part is seen, the share a
    model edge explains (so a pose too small, sitting on the part's inner edges, is
    punished); their F-measure weighed by how unlikely the confirmations are by chance.
    Nothing depends on the region a hypothesis came from, so hypotheses of all generators
    compare. The poses are projected together and counted in one compiled call. Outlines of
    curved faces (not sharp edges) are soft silhouettes, whose image edge lies up to a few
    pixels inside them where the face darkens at grazing light: they are looked up within
    ``pose.outline_pixels``, the sharp edges within ``pose.inlier_pixels``.
    """
    return frame.evidence.scores_of(pose_counts(graph, R, t, frame, p))


def pose_surprises(graph: AspectGraph, R: np.ndarray, t: np.ndarray, frame: "Frame", p: PoseParams) -> np.ndarray:
    """For B poses (B, 3, 3), (B, 3): the evidence against chance their confirmations carry,
    nats (``EdgeEvidence.surprises_of``), 0 where ``pose_scores`` is 0 for the pose's place
    or size. Unlike the score's shares it grows with the confirmed length: a pose that
    projects smaller and sits on the part's own edges can score a larger share than the
    part's truth hidden in part, but it explains less of the image."""
    return frame.evidence.surprises_of(pose_counts(graph, R, t, frame, p))


def pose_counts(graph: AspectGraph, R: np.ndarray, t: np.ndarray, frame: "Frame", p: PoseParams) -> np.ndarray:
    """(B, 8) ``EdgeEvidence.counts`` of B poses' visible model edges, projected together and
    counted in one compiled call; zeros for a pose behind the camera."""
    ahead = np.nonzero(np.asarray(t)[:, 2] > 0)[0]
    rows, pose_of_row = visible_rows(graph, R[ahead], t[ahead])
    model_px = project_each(frame.camera, graph.seg_3d[rows], R[ahead][pose_of_row], t[ahead][pose_of_row])
    spans = np.zeros(len(R) + 1, np.int64)
    spans[ahead + 1] = np.bincount(pose_of_row, minlength=len(ahead))
    return frame.evidence.counts(model_px, np.cumsum(spans), p.inlier_pixels, p.min_margin_pixels,
                                 p.min_size_pixels, graph.seg_kind[rows] != SHARP, p.outline_pixels, p.seen_pixels)


def scored_tolerances(graph: AspectGraph, p: PoseParams) -> tuple[float, ...]:
    """The tolerances, pixels, at which ``pose_scores`` looks a graph's edges up: the maps
    ``Frame.detect`` builds with the image's edges (``pose.outline_pixels`` only for a part
    with curved faces)."""
    curved = bool(np.any(graph.seg_kind != SHARP))
    return LookUp.of(p.inlier_pixels, p.outline_pixels if curved else None, p.seen_pixels).tolerances


@dataclass(frozen=True)
class LookUp:
    """The tolerances a score reads, pixels, in their layers' order, and which layer each
    reader takes: the look-up tolerance first; the outlines' own where there are outlines
    (``outline_px`` not None) and it differs, read by soft edges (else they read layer 0);
    the seen cells' where it is wider than the look-up (else ``seen_layer`` is -1 and cells
    are seen at the look-up tolerances alone)."""

    tolerances: tuple[float, ...]
    outline_layer: int
    seen_layer: int

    @classmethod
    def of(cls, inlier_px: float, outline_px: float | None, seen_px: float) -> "LookUp":
        outline = () if outline_px is None or outline_px == inlier_px else (float(outline_px),)
        seen = (float(seen_px),) if seen_px > inlier_px else ()
        tolerances = (float(inlier_px),) + outline + seen
        return cls(tolerances, len(outline), len(tolerances) - 1 if seen else -1)


def visible_rows(graph: AspectGraph, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``graph.seg_3d`` visible at each of B poses (the nearest view's), all
    poses' in one array, and the pose (0 to B - 1) of each row."""
    views = graph.nearest_views(R, t)
    starts, counts = graph.seg_offsets[views], np.diff(graph.seg_offsets)[views]
    rows = np.repeat(starts - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
    return rows, np.repeat(np.arange(len(views)), counts)


def project_each(camera: Camera, points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pixels of model points (N, ..., 3) each seen with its own pose R (N, 3, 3), t (N, 3),
    all in one projection; without lens distortion in numpy, 20x faster than OpenCV's
    ``projectPoints`` (50,000 points: 0.8 against 18 ms), which costs per point."""
    cam = np.einsum("nij,n...j->n...i", R, points) + t.reshape((len(t),) + (1,) * (points.ndim - 2) + (3,))
    return camera.project_model(cam, np.eye(3), np.zeros(3)) if camera.has_distortion else camera.project(cam)


def pose_shares(graph: AspectGraph, R: np.ndarray, t: np.ndarray, frame: "Frame",
                p: PoseParams) -> tuple["Shares", float, float]:
    """The ``Shares`` behind one pose's score (``pose_scores``, without its size floor), and
    the diagonal and the edge length of its projected visible model edges, pixels: what the
    estimate reports beside the score."""
    rows = graph.visible_segments(R, t)
    model_px = frame.camera.project_model(graph.seg_3d[rows], R, t)
    shares = frame.evidence.shares(model_px, p.inlier_pixels, p.min_margin_pixels, graph.seg_kind[rows] != SHARP,
                                   p.outline_pixels, p.seen_pixels)
    if len(model_px) == 0:
        return shares, 0.0, 0.0
    diagonal = float(np.hypot(*np.ptp(model_px.reshape(-1, 2), axis=0)))
    length = float(np.linalg.norm(model_px[:, 1] - model_px[:, 0], axis=1).sum())
    return shares, diagonal, length


@dataclass
class EdgePairs:
    """The seed paper's pairs at a pose: the visible model edges of the nearest view matched
    to image lines within ``ERROR_RATIO_REACH`` inlier distances; the nearest group lies
    within ``pose.inlier_pixels``."""

    error_ratio: float  # share of the visible model edges outside the nearest group (CONVENTIONS.md)
    n_matched: int
    n_nearest: int
    image_segments: np.ndarray  # (n_nearest, 2, 2) pixels
    model_segments: np.ndarray  # (n_nearest, 2, 2) pixels, projected with the pose


def edge_pairs(graph: AspectGraph, R: np.ndarray, t: np.ndarray, frame: "Frame", p: EstimatorParams) -> EdgePairs:
    """``EdgePairs`` of one pose. Model edges that project shorter than the line detector's
    minimum length cannot be found in any image and are left out."""
    camera = frame.camera
    visible = graph.seg_3d[graph.visible_segments(R, t)]
    lengths = np.linalg.norm(np.diff(camera.project_model(visible, R, t), axis=1), axis=2)[:, 0]
    visible = visible[lengths >= p.edges.min_length_fraction * np.hypot(camera.width, camera.height)]
    tolerance = p.pose.inlier_pixels / camera.focal
    model_index, image_index, distances = nearest_lines(project_normalised(visible, R, t), frame.segments_n,
                                                        ERROR_RATIO_REACH * tolerance)
    nearest = distances <= tolerance
    return EdgePairs(error_ratio=1.0 - float(nearest.sum()) / max(len(visible), 1),
                     n_matched=len(model_index), n_nearest=int(nearest.sum()),
                     image_segments=frame.segments_px[image_index[nearest]],
                     model_segments=camera.project_model(visible[model_index][nearest], R, t))


class Shares(NamedTuple):
    """What the image says about one pose (``EdgeEvidence.shares``), each in [0, 1]."""

    #: of the projected visible model edge length, the share like edge pixels confirm
    #: beyond what chance would confirm there
    confirmed: float
    #: of the edge pixels inside the grown outline where the part is seen, the share that
    #: lie on a projected model edge
    explained: float
    #: how unlikely the confirmations are by chance: 1 - exp(-length x KL / SIGNIFICANT_PIXELS)
    significance: float
    #: of the probe points beyond the ends of the model edges, the share like edges confirm
    #: beyond chance: the image's edges run on where the model's end
    run_on: float = 0.0

    @property
    def score(self) -> float:
        """The F-measure of the two shares, weighed by the significance and lowered by the
        run-on (``EdgeEvidence.RUN_ON_WEIGHT``)."""
        return float(combined_score(*self))


def combined_score(confirmed: float | np.ndarray, explained: float | np.ndarray, significance: float | np.ndarray,
                   run_on: float | np.ndarray) -> float | np.ndarray:
    """``Shares.score`` of floats or, element by element, of arrays."""
    f = 2 * confirmed * explained / np.maximum(confirmed + explained, 1e-12)
    return f * significance * np.maximum(1.0 - EdgeEvidence.RUN_ON_WEIGHT * run_on, 0.0)


def beyond_chance(confirmed: float | np.ndarray, expected: float | np.ndarray,
                  length: float | np.ndarray) -> float | np.ndarray:
    """The a-contrario share: of ``length`` (model points, or pixels of model length), what
    is confirmed beyond the ``expected`` amount chance confirms there, in [0, 1]; of floats
    or, element by element, of arrays."""
    return np.maximum(confirmed - expected, 0.0) / np.maximum(length - expected, 1e-12)


def kl_divergence(share: float | np.ndarray, chance: float | np.ndarray) -> np.ndarray:
    """KL divergence (nats) of a Bernoulli of ``share`` from one of ``chance``, 0 when the
    share is no more than chance: per sample, the exponent of the Chernoff bound on the
    probability that chance alone confirms this share. Element by element on arrays."""
    capped, floored = np.minimum(share, 1.0 - 1e-12), np.maximum(chance, 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):  # where share <= chance, dropped below
        kl = capped * np.log(capped / floored) + (1.0 - capped) * np.log((1.0 - capped) / (1.0 - floored))
    return np.where(share <= chance, 0.0, kl)


class LookUpMaps(NamedTuple):
    """``EdgeEvidence.maps``: per tolerance (``tolerances``) and direction bin, 1 where a
    like edge pixel lies within the tolerance (``near``, uint8) and the share of such pixels
    in the ``EdgeEvidence.CHANCE_WINDOW`` square about each pixel (``chance``, float32), each
    (T, BINS, rows, cols), over a window of the image with a one-pixel border (pixel (x, y)
    at (x + 1, y + 1)): ``window`` (4,) int64 its first row and column there, and the
    image's height and width. Outside the window both are 0, and so are the window's
    outermost rows and columns: a look-up clipped into the window reads what the whole
    image's maps hold (``kernels._in_window``)."""

    tolerances: tuple[float, ...]
    near: np.ndarray
    chance: np.ndarray
    window: np.ndarray

    def at(self, bins: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Layer 0's ``near`` (bool) and ``chance`` of direction ``bins`` at pixels (x, y)
        of the bordered image (int arrays, within it)."""
        rows, cols = self.near.shape[2:]
        y, x = np.clip(y - self.window[0], 0, rows - 1), np.clip(x - self.window[1], 0, cols - 1)
        return self.near[0][bins, y, x] != 0, self.chance[0][bins, y, x]


class NearestEdges(NamedTuple):
    """``EdgeEvidence.nearest_like``: per direction bin and pixel of a window of the image,
    the nearest like edge pixel, as ``labels`` (BINS, rows, cols) int32, rows of ``table``
    (L, 2) float, its x, y (row 0 lies far outside the image, for a bin without pixels);
    the window's first row and column in the image are ``origin`` (2,) int64. The order of
    ``kernels.nearest_like_edge``'s first arguments."""

    labels: np.ndarray
    origin: np.ndarray
    table: np.ndarray


class EdgeEvidence:
    """What the image says about edges, prepared once per image for scoring poses.

    Built from the Canny edge pixels, not from the Hough segments: a faint or curved edge
    that the line detector dropped still has its pixels, and a score counted on pixels
    separates right from wrong poses far better (docs/DECISIONS.md).

    * ``supports`` (model -> image): share of the projected model edge length within
      ``tolerance`` of an edge pixel of like direction (oriented chamfer: each model point
      looks up whether an edge pixel in its direction bin or the two next to it is that
      near), not corrected for chance.
    * ``confirmed_beyond_chance``: the same look-up once per short piece, corrected for
      chance as *confirmed* below: the twin check compares poses by it on the edges that
      tell them apart.
    * ``shares``, the score's three parts (``Shares``), counted in one compiled pass per
      pose, a batch of poses per call (``counts``, ``kernels.pose_evidence_kernel``, GIL released):
      - *confirmed*: the same look-ups, corrected for chance the a-contrario way: a model
        point's chance of being confirmed is the share of pixels near a like edge in the
        ``CHANCE_WINDOW`` square around it (``chance``, once per image), and the share is
        (confirmed - expected) / (length - expected). Dense clutter or texture confirms a
        wrong pose by chance, and then expects as much: the share stays near 0. Segments
        marked *soft* are looked up within a tolerance of their own, their chance counted
        at it (*explained* draws every segment within ``tolerance``: drawn wider too, the
        left-out parts got more wrong detections among clutter, docs/results/wall.md).
      - *explained*: of the edge pixels inside the projected part's convex outline, grown
        by ``OUTLINE_MARGIN`` (at least ``min_margin_px``), those within ``tolerance`` of a
        projected model edge, counted only in *seen* cells (``SEEN_CELL`` squares where at
        least half the model length is confirmed beyond chance, at the look-up tolerance
        or at a wider ``seen_tolerance_px`` (``pose.seen_pixels``); a cell without model edges takes the cells up to
        ``SEEN_REACH`` away). An occluder hides model edges, so its own edges fall in cells
        that are not seen and do not count against the pose; a pose turned a few degrees
        off the part's features still has their edges beside its own, and the image's
        edges there count against it. The margin is what stops a small pose that fits one inner feature (a window
        of the part) from explaining everything it covers: the part's edges around the
        window lie next to the window's seen edges.
      - *significance*: 1 - exp(-length x KL(confirmed share || chance) / ``SIGNIFICANT_PIXELS``),
        the Chernoff bound on chance producing the confirmations, made a share. A small
        pose has few edge pixels to show, so it must match cleanly to be believed; a pose
        far too large finds little of its length confirmed. The score is the F-measure of
        the two shares times the significance (``Shares.score``).
      - *run-on*: beyond each end of the pose's visible model edges, along them and off
        every other model edge (``kernels.run_on_kernel``), the share of probe points a like
        edge confirms, beyond chance as *confirmed*. A pose too small or too far sits on
        pieces of the part's longer edges, which run on past its ends; occlusion cuts edges
        short and adds none; clutter only by chance. The score is lowered by it.

    Both run hundreds of times per image and only ask whether a distance is within
    ``tolerance``, so none computes distances: with OpenCV's 3x3 chamfer distance
    (``cv2.distanceTransform(..., DIST_L2, 3)``, an exact shortest path in integer steps)
    "within r of a set" is the set dilated by the chamfer ball of radius r
    (``chamfer_ball``), several times cheaper than the transform. ``maps`` dilates,
    once per tolerance, the edge pixels of each direction bin together with the two next
    to it, so that a model point needs one look-up.
    """

    #: 22.5 degree direction bins, an edge pixel alike when in the same or a neighbouring
    #: bin: Sobel directions on a blurred edge scatter by several degrees, and more at corners
    BINS = 8
    #: the outline grows by a fifth, so that edges just outside a pose that projects a
    #: little small still count against it
    OUTLINE_MARGIN = 0.2
    #: the window of the local edge density that gives a model point's chance of being
    #: confirmed, pixels: local enough for a patch of texture, wide enough that a pose's
    #: own edge fills little of it (61 measured no better, docs/results/verification.md)
    CHANCE_WINDOW = 31
    #: cells of this many pixels decide where the part is seen (``kernels.pose_evidence_kernel``);
    #: a cell holding no model edge is judged by those up to ``SEEN_REACH`` cells away, so
    #: that the outline's margin next to a seen model edge still counts
    SEEN_CELL = 16
    SEEN_REACH = 2
    #: the confirmed evidence, in pixels of model length times nats of KL divergence from
    #: chance, at which the significance reaches 1 - 1/e: a part perfectly confirmed where
    #: chance is 1/4 (1.4 nats a pixel) needs about 115 px of edge for that, 350 px for 0.95.
    #: With samples 4 px apart counted as independent, that bounds the chance of the match
    #: by e^-40; chosen on the tuning parts against 320 and 480 (docs/results/verification.md)
    SIGNIFICANT_PIXELS = 160.0
    #: the run-on's probes reach past each end of a model edge this share of its projected
    #: length, at least RUN_ON_PROBE[1] and at most RUN_ON_PROBE[2] pixels, for model edges
    #: at least RUN_ON_MIN_LENGTH long (shorter ones are pieces of curves, their ends joined)
    RUN_ON_PROBE = (0.25, 6.0, 30.0)
    RUN_ON_MIN_LENGTH = 10.0
    #: ``nearest_like`` builds the whole image's labels when the window it needs covers more
    #: than this share of it: an image with edges that spread (clutter, occlusion) aligns its
    #: hypotheses from wide radii, which need all of it, and would build a large window twice
    WHOLE_LABELS_SHARE = 0.5
    #: the score is multiplied by 1 - RUN_ON_WEIGHT x run-on: on the tuning parts right poses
    #: show a run-on of at most 0.12 (99 % below 0.08), wrong poses too far a median of 0.2
    #: (docs/results/verification.md)
    RUN_ON_WEIGHT = 1.0

    def __init__(self, edge_map: np.ndarray, gradient_x: np.ndarray, gradient_y: np.ndarray):
        """From Canny's edge map and the image gradient it was found on (``ImageEdges``)."""
        self.shape = edge_map.shape
        self.edges = edge_map > 0
        # row-major like np.nonzero, ten times faster and without the GIL
        found = cv2.findNonZero(self.edges.view(np.uint8))
        #: the edge pixels (x, y) and the direction each edge runs in, modulo pi (across the
        #: gradient): the pre-filter's picture of an image region
        self.pixels = np.zeros((0, 2), np.intp) if found is None else found.reshape(-1, 2).astype(np.intp)
        cols, rows = self.pixels[:, 0], self.pixels[:, 1]
        dx, dy = gradient_x[rows, cols], gradient_y[rows, cols]
        #: the columns of row y's edge pixels are ``columns[row_starts[y]:row_starts[y + 1]]``,
        #: ascending: the scores count edge pixels row by row (contiguous, as the kernel was
        #: warmed with: a column of the pixels is a strided view)
        self.row_starts, self.columns = np.searchsorted(rows, np.arange(self.shape[0] + 1)), np.ascontiguousarray(cols)
        self.directions = np.mod(np.arctan2(dy, dx) + np.pi / 2, np.pi)
        self._bins = (self.directions / np.pi * self.BINS).astype(int) % self.BINS
        #: per direction bin b, the edge pixels of bins b - 1, b and b + 1
        self.like_edges = np.zeros((self.BINS,) + self.shape, np.uint8)
        for step in (-1, 0, 1):
            self.like_edges[(self._bins + step) % self.BINS, rows, cols] = 1
        self._maps: dict[tuple[float, ...], LookUpMaps] = {}  # tolerances -> maps()
        self._nearest_like: NearestEdges | None = None  # nearest_like(), built on first use
        self._nearest_reach = 0.0  # the reach of _nearest_like's window
        self._nearest_lock = threading.Lock()  # the refinement's threads share one image's evidence
        self._filling: tuple = ()  # the maps and the nearest-edge labels bin_jobs' jobs fill

    def bin_jobs(self, tolerances: tuple[float, ...] = ()) -> list[Callable[[], np.ndarray | None]]:
        """One job per direction bin building its piece of ``nearest_like`` and of the
        ``maps`` at ``tolerances``: OpenCV calls, which release the GIL, so that the bins run
        on several threads (``Frame.detect``). The maps are filled in place, the table's
        pieces returned: hand them to ``adopt`` once every job ran, before any other use of
        the evidence. The same maps as built on first use; the table reaches the widest of
        ``tolerances`` (the polish pairs within the look-up tolerance), the whole image without
        them."""
        # left unset here, each bin's job setting all of its own: zeroing the maps (about 35 MB
        # at two tolerances on a whole 640 x 480 image) cost the calling thread 1.5-2 ms an image
        reach = max(tolerances, default=math.inf)
        self._filling = (self._unset_maps(tuple(tolerances)), *self._unset_labels(reach))
        return [partial(self._fill_bin, b, *self._filling[:3]) for b in range(self.BINS)]

    def adopt(self, nearest_pieces: list[np.ndarray | None]) -> None:
        """Keep the maps ``bin_jobs`` filled and the nearest-edge table of its jobs' results."""
        maps, labels, origin, reach = self._filling
        with self._nearest_lock:
            self._nearest_like = NearestEdges(labels, origin, self._nearest_table(nearest_pieces))
            self._nearest_reach = reach
        if maps.tolerances:
            self._maps[maps.tolerances] = maps

    def _fill_bin(self, b: int, maps: "LookUpMaps", labels: np.ndarray, origin: np.ndarray) -> np.ndarray | None:
        """Direction bin ``b``'s rows of the ``maps`` and of the nearest-edge ``labels`` (from
        ``origin``), every element (``bin_jobs`` leaves them unset); its piece of the table
        (``_nearest_bin``)."""
        self._fill_maps(b, maps)
        return self._nearest_bin(b, labels, origin)

    def orientation_bin(self, segments: np.ndarray) -> np.ndarray:
        return self._bins_of(segments[:, 1] - segments[:, 0])

    def _bins_of(self, d: np.ndarray) -> np.ndarray:
        return (np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi) / np.pi * self.BINS).astype(int) % self.BINS

    def supports(self, model_px: np.ndarray, spans: np.ndarray, tolerance_px: float) -> np.ndarray:
        """The model -> image share (class doc) of several poses at once, segments
        ``spans[b]:spans[b + 1]`` of ``model_px`` (pixels) belonging to pose b: the look-ups
        of all poses run together, each pose's sums separately (the same sums as alone)."""
        h, w = self.shape
        delta = model_px[:, 1] - model_px[:, 0]
        lengths = np.sqrt((delta * delta).sum(axis=1))
        # a point every 2 pixels, at most 2000 per segment (a pose far too close projects huge)
        counts = np.clip(np.ceil(lengths / 2.0).astype(int), 1, 2000)
        seg_idx, frac = samples_along(counts)
        pts = model_px[:, 0][seg_idx] + frac[:, None] * delta[seg_idx]
        weight = (lengths / counts)[seg_idx]
        x, y = np.clip(np.rint(pts).astype(int) + 1, 0, [w + 1, h + 1]).T
        near = self._holding((tolerance_px,))[0].at(self._bins_of(delta)[seg_idx], x, y)[0]
        out = np.zeros(len(spans) - 1)
        point_spans = np.concatenate([[0], np.cumsum(counts)])[spans]
        for b, (lo, hi) in enumerate(zip(point_spans[:-1], point_spans[1:])):
            if hi > lo:
                out[b] = weight[lo:hi][near[lo:hi]].sum() / max(weight[lo:hi].sum(), 1e-12)
        return out

    def confirmed_beyond_chance(self, pieces: np.ndarray, tolerance_px: float) -> float:
        """The share of short pieces (N, 2, 2), pixels, each looked up once at its centre, that
        like edges confirm beyond what chance would confirm there (``chance``): a piece on
        clutter or texture is not confirmed by it. 0 for no pieces."""
        if len(pieces) == 0:
            return 0.0
        h, w = self.shape
        x, y = np.clip(np.rint(pieces.mean(axis=1)).astype(int) + 1, 0, [w + 1, h + 1]).T
        near, chance = self._holding((tolerance_px,))[0].at(self.orientation_bin(pieces), x, y)
        return float(beyond_chance(near.sum(), chance.sum(), len(pieces)))

    def maps(self, tolerances: tuple[float, ...]) -> "LookUpMaps":
        """The ``LookUpMaps`` at ``tolerances``: per tolerance and direction bin, the pixels
        within the tolerance of a like edge pixel (``like_edges`` dilated by the chamfer ball)
        and the chance map of that (``_boxed``). Built on first use unless ``bin_jobs`` built
        them; cached per tuple of tolerances."""
        if tolerances not in self._maps:
            maps = self._unset_maps(tolerances)
            for b in range(self.BINS):
                self._fill_maps(b, maps)
            self._maps[tolerances] = maps
        return self._maps[tolerances]

    def _unset_maps(self, tolerances: tuple[float, ...]) -> "LookUpMaps":
        """``LookUpMaps`` at ``tolerances``, allocated over their window, values unset.

        Both maps are 0 farther than the widest tolerance's chamfer ball plus half the
        ``CHANCE_WINDOW`` from every edge pixel: the window is the edge pixels' bounding box
        grown by that and one pixel more, all 0, so that a look-up clipped into it reads the
        same as the whole image's map (a clean image's part covers a tenth to a third of it,
        and builds that much). Every bin shares the window, so the maps stack."""
        h, w = self.shape
        if len(self.pixels) and tolerances:
            top, left, bottom, right = self._edge_box(
                chamfer_ball(max(tolerances)).shape[0] // 2 + self.CHANCE_WINDOW // 2 + 1)
            # in the coordinates of the image with its border: pixel (x, y) at (x + 1, y + 1)
            top, left, bottom, right = max(top + 1, 0), max(left + 1, 0), min(bottom + 1, h + 2), min(right + 1, w + 2)
        else:
            top, left, bottom, right = 0, 0, 1, 1  # the border's corner: 0 everywhere
        shape = (len(tolerances), self.BINS, bottom - top, right - left)
        return LookUpMaps(tolerances, np.empty(shape, np.uint8), np.empty(shape, np.float32),
                          np.array([top, left, h, w], np.int64))

    def _fill_maps(self, b: int, maps: "LookUpMaps") -> None:
        """Direction bin ``b``'s rows of ``maps``, every element: the image's border 0, the
        rest dilated (``cv2.dilate`` writes into the view of the stacked maps, no copy) and
        boxed. On the window alone both are the whole image's to the bit: a dilation has no
        like pixel beyond the window's edges to reach, and the box filter's reflected border
        at an edge inside the image reflects zeros (the window reaches half the box farther
        than the dilated pixels)."""
        top, left, h, w = (int(v) for v in maps.window)
        rows, cols = maps.near.shape[2:]
        # the window's part of the image, in the window's coordinates
        y0, y1, x0, x1 = max(1 - top, 0), min(h + 1 - top, rows), max(1 - left, 0), min(w + 1 - left, cols)
        for layers in (maps.near, maps.chance):
            layers[:, b, :y0], layers[:, b, y1:], layers[:, b, :, :x0], layers[:, b, :, x1:] = 0, 0, 0, 0
        if y1 <= y0 or x1 <= x0:
            return
        like = self.like_edges[b, top + y0 - 1:top + y1 - 1, left + x0 - 1:left + x1 - 1]
        for i, tolerance in enumerate(maps.tolerances):
            near = maps.near[i, b, y0:y1, x0:x1]
            cv2.dilate(like, chamfer_ball(tolerance), dst=near)
            self._boxed(near, maps.chance[i, b, y0:y1, x0:x1])

    def nearest_like(self, reach: float = math.inf, pool: WorkerPool = SERIAL) -> "NearestEdges":
        """Per direction bin and pixel within ``reach`` of an edge pixel, the nearest pixel of
        ``like_edges`` (``NearestEdges``): one distance transform with labels per bin (about
        3 ms a bin at 640 x 480) over a window of the image, the bins on the ``pool``'s
        threads. Built on first use (``bin_jobs`` builds it with the image's maps), and
        again over a wider window when asked for a wider ``reach`` than it has.

        Over the edge pixels' box, grown, the labels are the whole image's to the bit:
        OpenCV's two passes take a pixel's label from the first of its neighbours, in a fixed
        order, that ends its cheapest path; the cheapest paths from every edge pixel run
        monotone in x and y, within the box of their ends (a path with steps in opposite
        directions costs more in the 5x5 chamfer's integer weights, 65,536 / 91,750 /
        143,976), so none leaves the window, and a candidate from outside it always costs more
        than the cheapest from inside. Beyond the window, more than ``reach`` from every edge
        pixel, ``kernels.nearest_like_edge`` finds no edge pixel within its radius (at most
        the reach) either way."""
        with self._nearest_lock:
            if self._nearest_like is None or self._nearest_reach < reach:
                labels, origin, covered = self._unset_labels(reach)
                pieces = pool.map(lambda b: self._nearest_bin(b, labels, origin), range(self.BINS))
                self._nearest_like = NearestEdges(labels, origin, self._nearest_table(pieces))
                self._nearest_reach = covered
            return self._nearest_like

    def _unset_labels(self, reach: float) -> tuple[np.ndarray, np.ndarray, float]:
        """``nearest_like``'s labels (BINS, rows, cols) int32, left unset, over the edge
        pixels' box grown by ``reach`` and a pixel more (points rounded onto its pixels from
        up to half a pixel outside), their window's first row and column (``origin``), and
        the reach they cover: the whole image's (reach infinite) when that box covers more
        than ``WHOLE_LABELS_SHARE`` of the image. An image without edge pixels has none."""
        h, w = self.shape
        if not len(self.pixels):
            return np.empty((self.BINS, 0, 0), np.int32), np.zeros(2, np.int64), math.inf
        top, left, bottom, right = 0, 0, h, w
        if math.isfinite(reach):
            top, left, bottom, right = self._edge_box(int(math.ceil(reach)) + 1)
            top, left, bottom, right = max(top, 0), max(left, 0), min(bottom, h), min(right, w)
        if (bottom - top) * (right - left) > self.WHOLE_LABELS_SHARE * h * w:
            top, left, bottom, right, reach = 0, 0, h, w, math.inf
        return np.empty((self.BINS, bottom - top, right - left), np.int32), np.array([top, left], np.int64), reach

    def _edge_box(self, margin: int) -> tuple[int, int, int, int]:
        """The edge pixels' bounding box grown by ``margin`` pixels on every side, as (top,
        left, bottom, right) with exclusive ends, not clipped to the image."""
        (x_lo, y_lo), (x_hi, y_hi) = self.pixels.min(axis=0), self.pixels.max(axis=0)
        return int(y_lo) - margin, int(x_lo) - margin, int(y_hi) + margin + 1, int(x_hi) + margin + 1

    def _nearest_bin(self, b: int, labels: np.ndarray, origin: np.ndarray) -> np.ndarray | None:
        """Bin ``b``'s labels written into ``labels[b]`` (int32, its window from ``origin``),
        as rows of the whole table (``_nearest_table``), and its own label -> (x, y) table;
        None without pixels (``labels[b]`` 0: the far row)."""
        # the bin's like pixels in row-major order, as OpenCV numbers them 1, 2, ... (a scan of
        # the whole map by np.nonzero held the GIL 0.75 ms a bin); all lie in the window
        like = self.pixels[(self._bins - b + 1) % self.BINS <= 2]
        if not len(like):
            labels[b] = 0
            return None
        (top, left), (rows, cols) = origin, labels.shape[1:]
        # written in place: an array per bin, alive until the offsets are known, cost more in page faults
        cv2.distanceTransformWithLabels(1 - self.like_edges[b, top:top + rows, left:left + cols], cv2.DIST_L2, 5,
                                        labels=labels[b], labelType=cv2.DIST_LABEL_PIXEL)
        labels[b] += self._table_starts[b]  # here, on the bin's thread, not after every bin ran
        table = np.zeros((len(like) + 1, 2))  # label -> (x, y) of its pixel; label 0: none
        table[1:] = like
        return table

    @cached_property
    def _table_starts(self) -> np.ndarray:
        """Once per image (each bin's job reads it; threads racing to fill it compute the same
        array): where each bin's table begins in ``_nearest_table``'s: after the far-away row, the
        tables of the bins before it that have pixels, each as long as its pixels + 1."""
        per_bin = np.bincount(self._bins, minlength=self.BINS)
        like = per_bin + np.roll(per_bin, 1) + np.roll(per_bin, -1)  # bins b - 1, b and b + 1
        rows = np.where(like > 0, like + 1, 0)
        return 1 + np.cumsum(rows) - rows

    @staticmethod
    def _nearest_table(per_bin: list) -> np.ndarray:
        """``nearest_like``'s pixel table: a row far outside the image (label 0 of a bin without
        pixels), then the bins' ``_nearest_bin`` tables in order."""
        return np.concatenate([np.full((1, 2), -1e6)] + [table for table in per_bin if table is not None])

    @classmethod
    def grown_outline(cls, points: np.ndarray, min_margin_px: float) -> np.ndarray:
        """Convex hull of the points, grown about its centre by the margin (class doc;
        ``kernels.grown_outline``)."""
        return grown_outline(np.asarray(points, np.float64).reshape(-1, 2), float(min_margin_px), cls.OUTLINE_MARGIN)

    def shares(self, model_px: np.ndarray, tolerance_px: float, min_margin_px: float,
               soft: np.ndarray | None = None, soft_tolerance_px: float | None = None,
               seen_tolerance_px: float = 0.0) -> "Shares":
        """The ``Shares`` of a pose's projected visible model segments ``model_px``
        (S, 2, 2), pixels (class doc); the segments marked ``soft`` (S,) bool, outlines of
        curved faces, are looked up within ``soft_tolerance_px`` instead; cells are also
        seen at ``seen_tolerance_px`` when it exceeds ``tolerance_px``."""
        return self.shares_of(self.counts(model_px, np.array([0, len(model_px)]), tolerance_px, min_margin_px,
                                          soft=soft, soft_tolerance_px=soft_tolerance_px,
                                          seen_tolerance_px=seen_tolerance_px)[0])

    def shares_of(self, counts: np.ndarray) -> "Shares":
        """The ``Shares`` of a pose from its eight sums (``counts``)."""
        return Shares(*(float(share[0]) for share in self._shares(np.asarray(counts)[None])))

    def scores_of(self, counts: np.ndarray) -> np.ndarray:
        """(B,) ``Shares.score`` of B poses' sums (B, 8) at once (``pose_scores`` asks for
        ~800 an occluded image, whose Python one pose at a time held the GIL for 4-5 ms)."""
        return combined_score(*self._shares(np.asarray(counts)))

    def surprises_of(self, counts: np.ndarray) -> np.ndarray:
        """(B,) the confirmations' evidence against chance of B poses' sums (B, 8), nats: the
        model length times KL(confirmed share || chance), the exponent of the Chernoff bound
        on chance confirming as much (*significance*, class doc); 0 without model length."""
        length, confirmed, by_chance = np.asarray(counts, np.float64).T[:3]
        with np.errstate(divide="ignore", invalid="ignore"):  # the rows without length, zeroed below
            return np.where(length > 0, length * kl_divergence(confirmed / length, by_chance / length), 0.0)

    def _shares(self, counts: np.ndarray) -> np.ndarray:
        """(4, B): the ``Shares`` fields of B poses' sums (B, 8), all 0 for a pose without
        model length."""
        length, confirmed, by_chance, seen_edges, explained, probes, ran_on, ran_by_chance = counts.T
        surprise = self.surprises_of(counts)
        with np.errstate(divide="ignore", invalid="ignore"):  # the rows without length, zeroed below
            shares = np.array([beyond_chance(confirmed, by_chance, length),
                               np.where(seen_edges > 0, explained / seen_edges, 0.0),
                               1.0 - np.exp(-surprise / self.SIGNIFICANT_PIXELS),
                               beyond_chance(ran_on, ran_by_chance, probes)])
        return np.where(length > 0, shares, 0.0)

    def counted_pixels(self, model_px: np.ndarray, tolerance_px: float, min_margin_px: float,
                       soft: np.ndarray | None = None, soft_tolerance_px: float | None = None,
                       seen_tolerance_px: float = 0.0) -> np.ndarray:
        """(H, W) uint8: the edge pixels the explained share of ``shares`` counts at this pose,
        2 where a model edge explains them, 1 where none does, 0 elsewhere (for pictures of
        what lowers a pose's score, bench/explained_overlay.py)."""
        labels = np.zeros(self.shape, np.uint8)
        self.counts(model_px, np.array([0, len(model_px)]), tolerance_px, min_margin_px, soft=soft,
                    soft_tolerance_px=soft_tolerance_px, seen_tolerance_px=seen_tolerance_px, labels=labels)
        return labels

    def counts(self, model_px: np.ndarray, spans: np.ndarray, tolerance_px: float, min_margin_px: float,
               min_size_px: float = 0.0, soft: np.ndarray | None = None, soft_tolerance_px: float | None = None,
               seen_tolerance_px: float = 0.0, labels: np.ndarray | None = None) -> np.ndarray:
        """(B, 8) ``kernels.pose_evidence_kernel``'s five sums and ``kernels.run_on_kernel``'s
        three for B poses, pose b's segments
        ``model_px[spans[b]:spans[b + 1]]`` (pixels), those marked ``soft`` looked up within
        ``soft_tolerance_px``; zeros for a pose without segments or spanning less than
        ``min_size_px``; the counted pixels marked in ``labels`` if given (``counted_pixels``)."""
        model_px = np.ascontiguousarray(model_px, np.float64).reshape(-1, 2, 2)
        outline_px = soft_tolerance_px if soft is not None and np.any(soft) else None
        look_up = LookUp.of(tolerance_px, outline_px, seen_tolerance_px)
        reach_of = (np.asarray(soft, np.int64) * look_up.outline_layer if soft is not None
                    else np.zeros(len(model_px), np.int64))
        maps, layers = self._holding(look_up.tolerances)
        spans = np.asarray(spans, np.int64)
        sums, run_on = np.zeros((len(spans) - 1, 5)), np.zeros((len(spans) - 1, 3))
        pose_evidence_kernel(model_px, layers[reach_of], spans, float(min_size_px), maps.near, maps.chance,
                             maps.window, self.row_starts, self.columns, np.array(maps.tolerances),
                             float(min_margin_px), self.OUTLINE_MARGIN, self.SEEN_CELL, self.SEEN_REACH,
                             int(layers[look_up.seen_layer]) if look_up.seen_layer >= 0 else -1, sums,
                             np.zeros((0, 0), np.uint8) if labels is None else labels)
        # probes within a pixel beyond the look-up tolerance of another model edge are that edge's
        run_on_kernel(model_px, spans, maps.near, maps.chance, maps.window, *self.RUN_ON_PROBE,
                      self.RUN_ON_MIN_LENGTH, tolerance_px + 1.0, run_on)
        return np.hstack([sums, run_on])

    def _holding(self, tolerances: tuple[float, ...]) -> tuple["LookUpMaps", np.ndarray]:
        """Maps holding all ``tolerances``, the first of them first (the kernels draw and probe
        at layer 0), and each one's layer in them: the maps ``Frame.detect`` built for the
        graph's scores when they hold them (a batch without soft edges skips the outlines'
        layer), else built for these tolerances."""
        for held, maps in tuple(self._maps.items()):  # a copy: another thread may add maps
            if held[0] == tolerances[0] and set(tolerances) <= set(held):
                return maps, np.array([held.index(t) for t in tolerances], np.int64)
        return self.maps(tolerances), np.arange(len(tolerances), dtype=np.int64)

    def _boxed(self, near: np.ndarray, out: np.ndarray) -> None:
        """The share of set pixels of one bin's near map (uint8, no border) in the
        ``CHANCE_WINDOW`` square about each pixel, written into ``out`` (float32, a view into
        the stacked maps like the dilation's). The window's counts straight from the uint8 map, divided by its area
        in float32: the same shares to the bit as the normalised filter of the map made
        float (every count 0 to 961 rounds alike), a third cheaper; OpenCV's normalised
        filter of the uint8 map rounds differently."""
        window = (self.CHANCE_WINDOW, self.CHANCE_WINDOW)
        cv2.boxFilter(near, cv2.CV_32F, window, dst=out, normalize=False, borderType=cv2.BORDER_REFLECT)
        np.divide(out, np.float32(self.CHANCE_WINDOW**2), out=out)


@lru_cache(maxsize=16)
def chamfer_ball(radius: float) -> np.ndarray:
    """Structuring element of the offsets within ``radius`` (>= 0) of the centre by
    OpenCV's 3x3 L2 chamfer distance.

    That distance is a shortest path of axial and diagonal steps (both at least 0.95
    pixels), so a pixel's distance transform is the smallest chamfer norm of its offset
    to any set pixel, and ``distanceTransform(...) <= radius`` is exactly the set dilated
    by this ball. The ball comes from the same transform, so the two agree to the bit.
    """
    half = int(radius / 0.95) + 1
    canvas = np.full((2 * half + 1, 2 * half + 1), 255, np.uint8)
    canvas[half, half] = 0
    return (cv2.distanceTransform(canvas, cv2.DIST_L2, 3) <= radius).astype(np.uint8)
