"""Viewpoints on the view sphere around a part (model frame).

A viewpoint is a viewing direction (unit vector from the camera toward the model) and an
up vector (``geometry.default_up``); ``geometry.look_at_rotation`` turns the pair into
R_cam_model. Two samplings:

* ``fibonacci_directions`` (the default): a golden-spiral lattice whose neighbour spacing
  is close to a requested angular step everywhere. A longitude/latitude grid crowds its
  views at the poles, so to leave no direction farther from its nearest view it needs
  about 1.6 times as many views, and the online matcher pays for every one.
* ``lonlat_directions``: the seed paper's evenly spaced longitude/latitude grid (section 4,
  density K), kept to reproduce its experiments.
"""
from __future__ import annotations

import numpy as np

from .geometry import default_up, normalize

#: Median angle between golden-spiral neighbours in units of sqrt(4 pi / N), measured for
#: N from 50 to 5000 (a hexagonal packing would give 1.07; the spiral is a little denser).
_SPIRAL_SPACING = 0.955


def fibonacci_count(step_deg: float) -> int:
    """Number of golden-spiral views whose neighbours are about ``step_deg`` apart."""
    if not 0.0 < step_deg <= 90.0:
        raise ValueError(f"angular step must be in (0, 90] degrees, got {step_deg}")
    return max(2, int(round(4.0 * np.pi * (_SPIRAL_SPACING / np.radians(step_deg)) ** 2)))


def fibonacci_step(count: int) -> float:
    """The angular step (degrees) that gives about ``count`` golden-spiral views."""
    return float(np.degrees(_SPIRAL_SPACING * np.sqrt(4.0 * np.pi / count)))


def fibonacci_directions(step_deg: float) -> np.ndarray:
    """(V, 3) near-uniform unit viewing directions with neighbour spacing ~ ``step_deg``."""
    n = fibonacci_count(step_deg)
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def lonlat_directions(density: int) -> np.ndarray:
    """(V, 3) directions on the paper's grid: ``density`` longitudes 360/K apart and
    latitudes 180/K apart from pole to pole, each pole once: K * (K - 1) + 2 views."""
    if density < 2:
        raise ValueError(f"longitude/latitude density must be at least 2, got {density}")
    lon = np.arange(density) * (2.0 * np.pi / density)
    lat = -np.pi / 2.0 + np.arange(1, density) * (np.pi / density)
    lon_grid, lat_grid = np.meshgrid(lon, lat)
    ring = np.stack([np.cos(lat_grid) * np.cos(lon_grid), np.cos(lat_grid) * np.sin(lon_grid),
                     np.sin(lat_grid)], axis=-1).reshape(-1, 3)
    return np.concatenate([[[0.0, 0.0, -1.0]], ring, [[0.0, 0.0, 1.0]]])


def view_ups(directions: np.ndarray) -> np.ndarray:
    """(V, 3) up vector of every direction (``geometry.default_up``)."""
    return np.array([default_up(d) for d in np.asarray(directions, dtype=float)])


def nearest_views(directions: np.ndarray, query: np.ndarray, k: int = 3) -> np.ndarray:
    """Indices of the ``k`` sampled directions closest in angle to ``query``, nearest first.

    ``query`` is one direction (3,) -> (k,) or several (Q, 3) -> (Q, k).
    """
    directions = np.asarray(directions, dtype=float)
    query = normalize(query)
    k = min(k, len(directions))
    cos = np.atleast_2d(query) @ directions.T
    best = np.argpartition(-cos, k - 1, axis=1)[:, :k]
    order = np.argsort(-np.take_along_axis(cos, best, axis=1), axis=1)
    best = np.take_along_axis(best, order, axis=1)
    return best[0] if np.ndim(query) == 1 else best
