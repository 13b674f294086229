"""Colour regions: the places of a colour image that have the part's own surface colour.

A scanned model (a PLY mesh with vertex colours) knows what colour the part is; a STEP part
does not, and then this stage is skipped. Where it applies, the edge pixels outside the
regions are dropped before any other stage sees them (``Frame.detect``'s ``mask``), so that
the template search, the regions of the tetrads and the score look at the part's places
only: on the LM-O photographs the printed posters, the desk and the other objects gave any
edge template 0.5-0.65 where the true place scored 0.21-0.35 (docs/results/real_lmo.md).

The colour is compared as a chromaticity histogram (``chromaticity``), which a brighter or
dimmer light leaves alone. A pixel's likelihood is Swain and Ballard's histogram ratio
(Color indexing, IJCV 1991): the model's share of its bin over the image's share, at most
1; a colour the part has and the rest of the image rarely has scores 1, a colour everywhere
in the image scores its share of the model, so the regions stay small where the part's
colour is rare and grow to most of the image where it is common (a grey part on a grey
desk: nothing is lost, little is gained).

The regions of a coloured part split into places (the part, its shadow, other things of
like colour); ``colour_places`` ranks them by the part's colour they hold, for the estimate
to be made again within each of the first few alone (``Estimator``, ``edges.colour_places``).
"""
from __future__ import annotations

import cv2
import numpy as np

from ..chromaticity import chromaticity_bins, histogram, smoothed
from .image_edges import is_colour_image

#: the likelihood map is smoothed over this many pixels (odd): sensor noise moves single pixels' bins
SMOOTHING_PIXELS = 5
#: holes up to this many pixels (odd) in a region are closed: highlights and dark folds
#: of the part leave a different chromaticity inside its outline
CLOSING_PIXELS = 9
#: regions whose largest place holds more than this share of their pixels are one place (a grey
#: part's desk: 0.97-1.0 on the LM-O photos, a coloured part's largest 0.16-0.69): an estimate
#: within it alone would repeat the whole regions' one
ONE_PLACE_SHARE = 0.9
#: regions grow by this many pixels: the part's outline edges lie on the border of its
#: colour, blurred by the optics and by the edge stage's own blur
MARGIN_PIXELS = 5


def colour_likelihood(image: np.ndarray, model_histogram: np.ndarray) -> np.ndarray:
    """(H, W) float32 in [0, 1]: each pixel's histogram ratio (module doc), smoothed."""
    r, g = chromaticity_bins(image[:, :, :3])
    ratio = np.minimum(model_histogram / np.maximum(smoothed(histogram(r, g)), 1e-12), 1.0)
    return cv2.GaussianBlur(ratio[r, g], (SMOOTHING_PIXELS, SMOOTHING_PIXELS), 0)


def colour_regions(image: np.ndarray, model_histogram: np.ndarray | None, threshold: float,
                   min_pixels: float) -> np.ndarray | None:
    """(H, W) bool: the pixels whose smoothed likelihood reaches ``threshold``, holes closed,
    in regions of at least ``min_pixels``, grown by ``MARGIN_PIXELS``. None (use the whole
    image) when the model has no colour (``model_histogram`` None), the image is grey, or no
    region is that large (the part's colour is not in the image: not in view, or a light
    or camera that colours it otherwise, where dropping every edge would lose the part)."""
    if model_histogram is None or not is_colour_image(image):
        return None
    likely = (colour_likelihood(image, model_histogram) >= threshold).astype(np.uint8)
    likely = cv2.morphologyEx(likely, cv2.MORPH_CLOSE, np.ones((CLOSING_PIXELS, CLOSING_PIXELS), np.uint8))
    _, labels, stats, _ = cv2.connectedComponentsWithStats(likely, connectivity=8)
    large = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= min_pixels)
    large = large[large > 0]  # label 0 is the background
    if len(large) == 0:
        return None
    kept = np.isin(labels, large).astype(np.uint8)
    return cv2.dilate(kept, np.ones((2 * MARGIN_PIXELS + 1,) * 2, np.uint8)) > 0


def colour_places(image: np.ndarray, model_histogram: np.ndarray, regions: np.ndarray, count: int) -> list[np.ndarray]:
    """(H, W) bool masks of the 8-connected places of ``colour_regions``'s ``regions``, at most
    ``count``, those holding the most of the part's colour (the sum of the pixels' likelihood)
    first; none where the regions are one place (``ONE_PLACE_SHARE``)."""
    places, labels, stats, _ = cv2.connectedComponentsWithStats(regions.astype(np.uint8), connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]  # label 0 is the background
    if count == 0 or areas.max(initial=0) > ONE_PLACE_SHARE * areas.sum():
        return []
    colour = np.bincount(labels.ravel(), weights=colour_likelihood(image, model_histogram).ravel(),
                         minlength=places)[1:]
    return [labels == label + 1 for label in np.argsort(-colour, kind="stable")[:count]]
