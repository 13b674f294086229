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
from numba import njit

from ..metric_space import segment_lengths
from .kernels import chamfer_scores_kernel
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


def rotation_candidates(view_spectra: np.ndarray, image_hist: np.ndarray, count: int,
                        pool: WorkerPool = SERIAL) -> np.ndarray:
    """Candidate in-plane rotations (radians, [0, 2 pi)) turning views onto the image.

    view_spectra is ``orientation_spectra`` of the (V, B) view histograms: one circular
    cross-correlation per view by one inverse FFT. Each of the ``count`` best peaks
    (modulo pi) gives two candidates, phi and phi + pi. Returns (V, 2*count). The views
    are split among the ``pool``'s threads (row by row the same bits; the FFT releases
    the GIL).
    """
    image_spectrum = np.fft.rfft(image_hist)[None, :]

    def chunk(views: slice) -> np.ndarray:
        corr = np.fft.irfft(image_spectrum * view_spectra[views], n=ORIENTATION_BINS, axis=1)
        ranked = np.empty((len(corr), count), dtype=np.int64)
        ranked_peaks(corr, count, ranked)
        phi = ranked * (np.pi / ORIENTATION_BINS)
        return np.concatenate([phi, phi + np.pi], axis=1)

    return np.concatenate(pool.map(chunk, pool.split(len(view_spectra), ChamferPrefilter.MIN_CHUNK)))


@njit(nogil=True, cache=True)
def ranked_peaks(corr: np.ndarray, count: int, ranked: np.ndarray) -> None:
    """ranked[v]: the bins of the ``count`` highest peaks of corr[v] (bins at least as high as
    both cyclic neighbours), best first, ties to the lower bin; when fewer peaks, bin 0 (as
    ``count`` rounds of np.argmax over the peaks, each taken one set to -inf). One compiled
    pass, the GIL released: as numpy steps on the (V, 72) array, a dozen temporaries and
    their GIL hand-overs per region."""
    bins = corr.shape[1]
    peaks = np.empty(bins)
    for v in range(len(corr)):
        for b in range(bins):
            value = corr[v, b]
            left, right = corr[v, b - 1 if b > 0 else bins - 1], corr[v, b + 1 if b < bins - 1 else 0]
            peaks[b] = value if value >= left and value >= right else -np.inf
        for k in range(count):
            best = 0
            for b in range(1, bins):
                if peaks[b] > peaks[best]:
                    best = b
            ranked[v, k] = best
            peaks[best] = -np.inf


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
    #: fewest views per worker's chunk of a score: a shorter chunk costs more to hand over
    #: than it saves
    MIN_CHUNK = 128
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
        coarse = self.scores(maps, phis, self.COARSE_STRIDE, pool).ravel()
        keep = min(len(coarse), self.COARSE_KEEP * count)
        pairs = np.argpartition(coarse, keep - 1)[:keep] if keep < len(coarse) else np.arange(len(coarse))
        # contiguous, as the kernel was warmed with (unravel_index returns strided views)
        views, which = (np.ascontiguousarray(a) for a in np.unravel_index(pairs, phis.shape))
        turned = np.mod(phis[views, which].astype(np.float32), np.float32(2 * np.pi))[:, None]
        fine = self._scores_of(maps, views, turned, 1, pool)[:, 0]
        count = min(count, len(fine))
        best = np.argpartition(fine, count - 1)[:count]
        return views[best], which[best]

    def scores(self, maps: np.ndarray, phis: np.ndarray, stride: int = 1, pool: WorkerPool = SERIAL) -> np.ndarray:
        """(V, R) mean truncated oriented distance of view v turned by phis[v, r], over every
        ``stride``-th of the view's points (all by default)."""
        return self._scores_of(maps, np.arange(len(phis)), np.mod(phis.astype(np.float32), np.float32(2 * np.pi)),
                               stride, pool)

    def _scores_of(self, maps: np.ndarray, views: np.ndarray, phis: np.ndarray, stride: int,
                   pool: WorkerPool) -> np.ndarray:
        """(K, R) scores of view views[k] at the rotations phis[k] (float32, in [0, 2 pi)).

        Every score is over V x R x P points (10^5 to 10^6 at thousands of views): one
        compiled loop (``kernels.chamfer_scores_kernel``, GIL released, no temporaries) per
        chunk of rows, the chunks shared among the ``pool``'s threads. As numpy array
        steps it held the GIL between every step and built (V, R, P) temporaries.
        """
        cos_phi, sin_phi = np.cos(phis), np.sin(phis)  # numpy's float32 cosine, as the scores always had
        out = np.empty(phis.shape, np.float32)
        cell = 2.0 * self.EXTENT / self.GRID

        def chunk(rows: slice) -> None:
            chamfer_scores_kernel(maps, self.points, self.orientations, stride, views[rows], phis[rows],
                                  cos_phi[rows], sin_phi[rows], self.EXTENT, cell, self.TRUNCATE, out[rows])

        pool.map(chunk, pool.split(len(views), self.MIN_CHUNK))
        return out


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
