"""The visible surface of posed meshes, pixel by pixel: a CPU z-buffer.

No GPU or OpenGL is assumed, so this is a vectorised numpy rasteriser. Pixel centres sit at
integer coordinates as in OpenCV and vertices are projected with ``cv2.projectPoints``, so a
silhouette drawn here matches the projection every other stage uses to within a pixel. The
synthetic renderer shades it (``synthetic.render``); the estimator compares an image's grey
levels with the normals it gives at a pose (``online.appearance``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .camera import Camera
from .geometry import normalize

#: Triangles with a vertex closer than this to the camera plane (metres) are dropped whole:
#: there is no near-plane clipping, so scenes keep every object in front of the camera.
NEAR = 1e-3


@dataclass
class Posed:
    """A mesh (``vertices``, ``triangles``, per-vertex ``normals``; model frame, metres) at
    pose (R, t) in the camera frame: X_cam = R @ X_model + t."""

    mesh: object
    R: np.ndarray
    t: np.ndarray


@dataclass
class Raster:
    """The visible surface of a set of objects.

    ``depth`` (metres along the optical axis, inf on background) and ``labels`` (index of
    the visible object, -1 on background) are images; ``pixels`` (flat indices),
    ``points`` and ``normals`` (camera frame) describe the visible surface pixel by pixel.
    """

    depth: np.ndarray
    labels: np.ndarray
    pixels: np.ndarray
    points: np.ndarray
    normals: np.ndarray

    def facing_normals(self) -> np.ndarray:
        """``normals`` turned to face the viewer: a normal interpolated across a curved
        silhouette can turn slightly away."""
        view = -normalize(self.points)
        return np.where(np.einsum("ij,ij->i", self.normals, view)[:, None] < 0, -self.normals, self.normals)


def rasterize(camera: Camera, objects: Sequence[Posed]) -> Raster:
    """Z-buffer the front faces of all objects; the nearest surface wins each pixel centre."""
    h, w = camera.height, camera.width
    verts, normals, tris, owner = [], [], [], []
    offset = 0
    for index, obj in enumerate(objects):
        R = np.asarray(obj.R, dtype=float)
        verts.append(obj.mesh.vertices @ R.T + np.asarray(obj.t, dtype=float).reshape(3))
        normals.append(obj.mesh.normals @ R.T)
        tris.append(obj.mesh.triangles + offset)
        owner.append(np.full(len(obj.mesh.triangles), index, dtype=np.int16))
        offset += len(obj.mesh.vertices)
    P = np.concatenate(verts)
    N = np.concatenate(normals)
    T = np.concatenate(tris)
    owner = np.concatenate(owner)

    depth = np.full(h * w, np.inf)
    labels = np.full(h * w, -1, dtype=np.int16)
    empty = Raster(depth.reshape(h, w), labels.reshape(h, w), np.zeros(0, dtype=np.int64),
                   np.zeros((0, 3)), np.zeros((0, 3)))

    # Keep front faces entirely in front of the camera (geometric normal towards the eye).
    p0, p1, p2 = P[T[:, 0]], P[T[:, 1]], P[T[:, 2]]
    front = np.einsum("ij,ij->i", np.cross(p1 - p0, p2 - p0), p0) < 0
    front &= (P[T, 2] > NEAR).all(axis=1)
    T, owner = T[front], owner[front]
    if len(T) == 0:
        return empty

    uv = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K,
                           camera.dist_coeffs)[0].reshape(-1, 2)
    frag_tri, frag_x, frag_y, bary = _fragments(uv[T], w, h)
    if len(frag_tri) == 0:
        return empty

    # Perspective-correct depth: 1/z is affine in the image.
    inv_z = 1.0 / P[T, 2]
    frag_inv_z = np.einsum("ij,ij->i", bary, inv_z[frag_tri])
    frag_z = 1.0 / frag_inv_z
    pix = frag_y * w + frag_x
    np.minimum.at(depth, pix, frag_z)
    winner = np.full(h * w, -1, dtype=np.int64)
    nearest = np.flatnonzero(frag_z == depth[pix])
    winner[pix[nearest]] = nearest  # ties (shared edges) resolve to any of the equals
    pixels = np.flatnonzero(winner >= 0)
    win = winner[pixels]
    tri = T[frag_tri[win]]
    weights = bary[win] * inv_z[frag_tri[win]] / frag_inv_z[win, None]
    points = np.einsum("ij,ijk->ik", weights, P[tri])
    nrm = normalize(np.einsum("ij,ijk->ik", weights, N[tri]))
    labels[pixels] = owner[frag_tri[win]]
    return Raster(depth.reshape(h, w), labels.reshape(h, w), pixels, points, nrm)


def _fragments(tri_uv: np.ndarray, width: int, height: int):
    """Pixel centres covered by each 2D triangle, with their barycentric coordinates.

    Each triangle is walked row by row: the three edge half-planes give the exact span of
    covered columns in a row, so the work is proportional to the covered area, not to the
    triangles' bounding boxes (long slivers are common in CAD tessellations).
    """
    x, y = tri_uv[..., 0], tri_uv[..., 1]
    area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    keep = np.abs(area) > 1e-12
    # Barycentric weight i = A_i * u + B_i * v + C_i (edge opposite vertex i over the area).
    j, k = [1, 2, 0], [2, 0, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        A = (y[:, j] - y[:, k]) / area[:, None]
        B = (x[:, k] - x[:, j]) / area[:, None]
        C = (x[:, j] * y[:, k] - x[:, k] * y[:, j]) / area[:, None]
    y0 = np.maximum(np.ceil(y.min(axis=1)), 0)
    y1 = np.minimum(np.floor(y.max(axis=1)), height - 1)
    keep &= (y1 >= y0) & (x.max(axis=1) >= 0) & (x.min(axis=1) <= width - 1)
    tri_ids = np.flatnonzero(keep)
    rows_per_tri = (y1 - y0 + 1)[tri_ids].astype(np.int64)
    row_tri = np.repeat(tri_ids, rows_per_tri)
    row_y = y0[row_tri] + _ramp(rows_per_tri)

    a, b, c = A[row_tri], B[row_tri], C[row_tri]
    level = b * row_y[:, None] + c  # weight_i = a_i * u + level_i >= 0 on this row
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = -level / a
    lower = np.where(a > 0, bound, -np.inf).max(axis=1)
    upper = np.where(a < 0, bound, np.inf).min(axis=1)
    flat_out = ((a == 0) & (level < 0)).any(axis=1)  # a row outside a horizontal edge
    x0 = np.maximum(np.ceil(lower), 0)
    x1 = np.minimum(np.floor(upper), width - 1)
    span = np.where(flat_out | (x1 < x0), 0, x1 - x0 + 1).astype(np.int64)

    frag_row = np.repeat(np.arange(len(span)), span)
    frag_x = (x0[frag_row] + _ramp(span)).astype(np.int64)
    frag_y = row_y[frag_row].astype(np.int64)
    frag_tri = row_tri[frag_row]
    bary = A[frag_tri] * frag_x[:, None] + B[frag_tri] * frag_y[:, None] + C[frag_tri]
    return frag_tri, frag_x, frag_y, bary


def _ramp(counts: np.ndarray) -> np.ndarray:
    """0, 1, ..., n-1 for every n in ``counts``, concatenated."""
    starts = np.cumsum(counts) - counts
    return np.arange(counts.sum()) - np.repeat(starts, counts)
