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

import itertools

import numpy as np
from scipy.spatial import cKDTree

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


#: the faces of the cube about the sphere that ``direction_cells`` divides, as the axis a
#: face looks along and the two axes of its (u, v): a direction d lies on face (axis, sign)
#: of its largest |component|, at u = d[a] / |d[axis]|, v = d[b] / |d[axis]| (the kernels'
#: ``kernels._direction_cell`` reads them in this order)
CUBE_FACES = ((0, 1, 2), (0, 1, 2), (1, 0, 2), (1, 0, 2), (2, 0, 1), (2, 0, 1))
#: added to each cell's angular reach, radians: rounding in the kernels' products and the
#: cell look-up is some 1e-15, so a view this much farther out can never win there
CELL_MARGIN_RAD = 1e-3
#: about this many views per cell of ``direction_cells``: each cell then holds some 9 that can
#: be nearest to one of its directions
CELL_VIEWS = 4


def direction_cells(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A look-up of unit ``directions`` (V, 3) by cells of the cube about the sphere: ``starts``
    (6 n^2 + 1,) and ``views``, the views of cell c being ``views[starts[c]:starts[c + 1]]``
    in ascending order, every view that can be the nearest (largest product) to some
    direction in the cell. Empty arrays where ``directions`` are not unit vectors: the
    kernels then scan every view.

    The view nearest to any direction d of a cell lies within 2 r + a of the cell's centre c,
    r the cell's reach from c (its farthest corner: the cells are bounded by great circles)
    and a the angle from c to the view nearest c: it is no farther from d than that view,
    r + a at most, and d lies within r of c. n = ceil(sqrt(V / ``CELL_VIEWS``)) cells a face
    side leave a few views to compare instead of all (``kernels._nearest_view``: 3.6 -> 0.1 us
    a pose at 2,500 views)."""
    directions = np.asarray(directions, dtype=float)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(directions) == 0 or not np.all(np.abs(np.linalg.norm(directions, axis=1) - 1.0) <= 1e-12):
        return empty
    n = int(np.ceil(np.sqrt(len(directions) / CELL_VIEWS)))
    edges = np.linspace(-1.0, 1.0, n + 1)
    middles = (edges[:-1] + edges[1:]) / 2
    faces = []
    for f, (axis, a, b) in enumerate(CUBE_FACES):
        def on_face(u, v, axis=axis, a=a, b=b, sign=1.0 if f % 2 == 0 else -1.0):
            d = np.empty(np.broadcast(u, v).shape + (3,))
            d[..., axis], d[..., a], d[..., b] = sign, u, v
            return d / np.linalg.norm(d, axis=-1, keepdims=True)
        centre = on_face(middles[:, None], middles[None, :])  # (n, n, 3): cell (i, j) at u i, v j
        corners = [on_face(edges[di:di + n, None], edges[None, dj:dj + n]) for di in (0, 1) for dj in (0, 1)]
        reach = np.max([np.arccos(np.clip(np.sum(centre * c, axis=-1), -1.0, 1.0)) for c in corners], axis=0)
        faces.append((centre.reshape(-1, 3), reach.ravel()))
    centres = np.concatenate([c for c, _ in faces])
    reach = np.concatenate([r for _, r in faces])
    tree = cKDTree(directions)
    chord, _ = tree.query(centres)
    nearest = 2.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0))
    bound = np.minimum(2.0 * reach + nearest + CELL_MARGIN_RAD, np.pi)
    members = tree.query_ball_point(centres, 2.0 * np.sin(bound / 2.0) + 1e-12, return_sorted=True)
    starts = np.zeros(len(members) + 1, np.int64)
    starts[1:] = np.cumsum([len(m) for m in members])
    return starts, np.fromiter(itertools.chain.from_iterable(members), np.int64, starts[-1])
