"""The pre-filter: which (view, in-plane rotation) pairs of the aspect graph are worth the
bipartite matching for one image region (``matching``), chosen for all views at once.

* In-plane rotation. The tetrad's two angles turn with the image, so the pair-wise
  matching is not rotation invariant, as the paper assumes. We search the rotation
  explicitly: the circular cross-correlation of the length-weighted orientation
  histograms of view and image (one FFT for all views) gives a few candidate rotations
  (each also turned by 180 degrees), and the assignment is solved at each candidate.
* Oriented chamfer distance. Kuhn-Munkres is cubic, so it does not run for every view:
  points sampled along every view's segments, turned by each view's candidate rotations,
  look up an oriented distance map of the image region (all views at once,
  ``ChamferPrefilter``); the closest (view, rotation) pairs go on to the assignment. The
  map is drawn from the region's Canny edge pixels, not from its line segments: holes,
  fillets and rounded outlines give no segment but do give edge pixels, and the view's
  chords of those curves then find their counterpart (docs/DECISIONS.md).
"""
from __future__ import annotations

import cv2
import numpy as np

from ..metric_space import segment_lengths
from .workers import SERIAL, WorkerPool

#: 2.5 degree bins over [0, pi): a candidate rotation is off by at most 1.25 degrees, which
#: the assignment tolerates and the similarity fit then removes
ORIENTATION_BINS = 72


def orientation_histogram(orient: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Length-weighted histogram (ORIENTATION_BINS,) of segment orientations modulo pi, smoothed."""
    bins = (orient / np.pi * ORIENTATION_BINS).astype(int) % ORIENTATION_BINS
    hist = np.bincount(bins, weights=lengths, minlength=ORIENTATION_BINS)
    kernel = np.array([0.25, 0.5, 1.0, 0.5, 0.25])  # +-5 degrees: Hough angles scatter by a few
    padded = np.concatenate([hist[-2:], hist, hist[:2]])
    return np.convolve(padded, kernel, mode="valid")


def orientation_spectra(view_hist: np.ndarray) -> np.ndarray:
    """Conjugate spectra of view orientation histograms (V, B) for ``rotation_candidates``:
    the views' half of the cross-correlation, computed once when the views are loaded."""
    return np.conj(np.fft.rfft(view_hist, axis=1))


def rotation_candidates(view_spectra: np.ndarray, image_hist: np.ndarray, count: int) -> np.ndarray:
    """Candidate in-plane rotations (radians, [0, 2 pi)) turning views onto the image.

    view_spectra is ``orientation_spectra`` of the (V, B) view histograms: one circular
    cross-correlation per view by one inverse FFT. Each of the ``count`` best peaks
    (modulo pi) gives two candidates, phi and phi + pi. Returns (V, 2*count).
    """
    corr = np.fft.irfft(np.fft.rfft(image_hist)[None, :] * view_spectra, n=ORIENTATION_BINS, axis=1)
    wrapped = np.concatenate([corr[:, -1:], corr, corr[:, :1]], axis=1)
    peaks = np.where((corr >= wrapped[:, :-2]) & (corr >= wrapped[:, 2:]), corr, -np.inf)
    ranked = np.empty((len(corr), count), dtype=int)
    rows = np.arange(len(corr))
    for k in range(count):  # best peak first, then the next best: a few argmax, no sort
        ranked[:, k] = best = np.argmax(peaks, axis=1)
        peaks[rows, best] = -np.inf
    phi = ranked * (np.pi / ORIENTATION_BINS)
    return np.concatenate([phi, phi + np.pi], axis=1)


class ChamferPrefilter:
    """Oriented chamfer distance of every view, at its candidate rotations, to a region.

    Views are sampled once as ``points_per_view`` points along their normalised segments
    (length-weighted). A region's oriented edge points (normalised, e.g. its edge pixels)
    are rasterised once into ``ORIENT_BINS`` distance maps, one per edge direction, over
    the normalised square [-EXTENT, EXTENT]^2. Scoring every (view, rotation) is then a
    gather over a (V, R, P) index array, cheap enough for thousands of views.
    """

    #: 30 degree direction bins, no neighbour bins looked up: wide enough that one edge in
    #: the view and in the image mostly share a bin despite the rotation candidates' steps
    #: and the views' spacing, narrow enough to keep crossing edges apart
    ORIENT_BINS = 6
    #: normalised coordinates put the part's outline within about +-1 (unit hull area); the
    #: square reaches twice that for elongated parts and a region whose centre is off
    EXTENT = 2.0
    #: cells of 4 / 96 = 0.042 normalised units, about matching.coverage_tolerance (0.04):
    #: the shortlist needs no finer distances than the ranking after it uses
    GRID = 96
    #: a point farther than a quarter of the part's size from any like edge has no
    #: counterpart; capping its distance keeps a few such points from outweighing the rest
    TRUNCATE = 0.25
    #: views per block of ``scores``: the (BLOCK, R, P) temporaries stay in the CPU cache
    BLOCK = 256
    #: the coarse stage scores every 4th point (8 of 32, still spread over the whole view)
    #: and keeps 16 x shortlist_size pairs for the full score, which then finds the same
    #: best pairs as scoring all in full (test_prefilter_shortlist_keeps_the_best_pairs_of_the_full_score)
    COARSE_STRIDE = 4
    COARSE_KEEP = 16

    def __init__(self, view_segments: list[np.ndarray], points_per_view: int = 32):
        pts, ori = [], []
        for segments in view_segments:
            p, o = spread_points(segments, points_per_view)
            pts.append(p)
            ori.append(o)
        self.points = np.stack(pts).astype(np.float32)  # (V, P, 2)
        self.orientations = np.stack(ori).astype(np.float32)  # (V, P) modulo pi

    @classmethod
    def distance_maps(cls, points: np.ndarray, orientations: np.ndarray) -> np.ndarray:
        """(ORIENT_BINS, GRID, GRID) truncated distance to the region's points (N, 2) of each
        direction bin (orientations modulo pi); a point falls in the cell the gather of
        ``scores`` reads, and points outside the square are left out."""
        cell = 2.0 * cls.EXTENT / cls.GRID
        col, row = np.floor((np.asarray(points, dtype=float) + cls.EXTENT) / cell).astype(np.int64).T
        inside = (col >= 0) & (col < cls.GRID) & (row >= 0) & (row < cls.GRID)
        bins = (np.asarray(orientations)[inside] / np.pi * cls.ORIENT_BINS).astype(int) % cls.ORIENT_BINS
        canvas = np.full((cls.ORIENT_BINS, cls.GRID, cls.GRID), 255, np.uint8)
        canvas[bins, row[inside], col[inside]] = 0
        maps = np.stack([cv2.distanceTransform(c, cv2.DIST_L2, 3) for c in canvas]) * np.float32(cell)
        return np.minimum(maps, np.float32(cls.TRUNCATE))

    def shortlist(self, maps: np.ndarray, phis: np.ndarray, count: int,
                  pool: WorkerPool = SERIAL) -> tuple[np.ndarray, np.ndarray]:
        """Views and rotation indices (in no particular order) of the ``count`` (view,
        rotation) pairs with the lowest score.

        Two stages: every pair is scored on every ``COARSE_STRIDE``-th of its points (still
        spread along the whole view), and only the ``COARSE_KEEP`` x ``count`` best go on to
        the full score: at 10,000 views the full score of every pair would cost most of an
        image's time. Both stages split their views between the ``pool``'s threads.
        """
        coarse = self.scores(maps, phis, slice(None, None, self.COARSE_STRIDE), pool).ravel()
        keep = min(len(coarse), self.COARSE_KEEP * count)
        pairs = np.argpartition(coarse, keep - 1)[:keep] if keep < len(coarse) else np.arange(len(coarse))
        views, which = np.unravel_index(pairs, phis.shape)
        turned = np.mod(phis[views, which].astype(np.float32), np.float32(2 * np.pi))[:, None]
        fine = np.concatenate(pool.map(
            lambda chunk: self._block_scores(maps, self.points[views[chunk]], self.orientations[views[chunk]],
                                             turned[chunk])[:, 0],
            pool.split(len(views), self.BLOCK // 2)))
        count = min(count, len(fine))
        best = np.argpartition(fine, count - 1)[:count]
        return views[best], which[best]

    def scores(self, maps: np.ndarray, phis: np.ndarray, points: slice = slice(None),
               pool: WorkerPool = SERIAL) -> np.ndarray:
        """(V, R) mean truncated oriented distance of view v turned by phis[v, r], over the
        view's ``points`` (all by default).

        Every step is over V x R x P points (10^5 to 10^6), so it runs in blocks of
        ``BLOCK`` views, whose temporaries stay in the cache, and the slow steps are
        avoided: one flat gather instead of a 3-index one, and no np.mod for the
        orientation (with phi in [0, 2 pi) the turned orientation is below 3 pi, and
        subtracting pi once or twice gives np.mod's result to the bit). The blocks are shared
        among the ``pool``'s threads (numpy releases the GIL inside each step).
        """
        phis = np.mod(phis.astype(np.float32), np.float32(2 * np.pi))
        out = np.empty(phis.shape, np.float32)

        def score_blocks(blocks: slice) -> None:
            for lo in range(blocks.start * self.BLOCK, min(blocks.stop * self.BLOCK, len(phis)), self.BLOCK):
                views = slice(lo, lo + self.BLOCK)
                out[views] = self._block_scores(maps, self.points[views, points], self.orientations[views, points],
                                                phis[views])

        pool.map(score_blocks, pool.split(-(-len(phis) // self.BLOCK)))
        return out

    def _block_scores(self, maps, points, orientations, phis):
        c, s = np.cos(phis)[..., None], np.sin(phis)[..., None]
        x, y = points[:, None, :, 0], points[:, None, :, 1]
        xr, yr = c * x - s * y, s * x + c * y  # (V, R, P)
        cell = 2.0 * self.EXTENT / self.GRID
        col = np.clip(((xr + self.EXTENT) / cell).astype(np.int32), 0, self.GRID - 1)
        row = np.clip(((yr + self.EXTENT) / cell).astype(np.int32), 0, self.GRID - 1)
        ori = orientations[:, None, :] + phis[..., None]
        half_turns = (ori >= np.float32(np.pi)).astype(np.float32) + (ori >= np.float32(2 * np.pi))
        ori -= np.float32(np.pi) * half_turns
        b = (ori / np.pi * self.ORIENT_BINS).astype(np.int32) % self.ORIENT_BINS
        outside = (np.abs(xr) > self.EXTENT) | (np.abs(yr) > self.EXTENT)
        dist = np.where(outside, self.TRUNCATE, maps.ravel()[(b * self.GRID + row) * self.GRID + col])
        return dist.mean(axis=2)


def spread_points(segments: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points evenly spaced along the total length of a segment set, and the
    orientation (modulo pi) of the segment each lies on."""
    lengths = segment_lengths(segments)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    at = (np.arange(count) + 0.5) / count * cum[-1]
    idx = np.clip(np.searchsorted(cum, at, side="right") - 1, 0, len(segments) - 1)
    frac = (at - cum[idx]) / np.maximum(lengths[idx], 1e-12)
    a, b = segments[idx, 0], segments[idx, 1]
    d = b - a
    return a + frac[:, None] * d, np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
