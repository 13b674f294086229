"""Verification beyond the edges: does the image's shading over the part's silhouette at a
pose look like the part's surface there?

A texture-less part's grey levels follow its surface normals under the scene's light: for a
convex Lambertian surface under any distant light they lie close to a combination of the
normals' spherical harmonics up to order 2 (Basri and Jacobs, PAMI 2003), so the light need
not be known. ``shading_fit`` is the share of the grey levels' spread over the silhouette
that such a combination explains, after leaving out the pixels that fit worst (an occluder, a
highlight, a reflection): near 1 where the normals at the pose are the part's, lower where a
wrong pose lays the silhouette over other faces, the background or clutter. On bench images
it told right found poses from wrong ones better than the edge evidence (AUC 0.87 against
0.75 for the confidence), and on the LM-O photos it preferred the truth to 136 of 171 wrong
estimates, the edge score to 48 (docs/results/verification.md, session 27). The confidence
weighs it (``confidence.FEATURES``), and ``pose.min_shading_fit`` may floor it.

Needs the part's surface in the aspect graph (``AspectGraph.surface``: graphs compiled since
session 27); a pose costs a few milliseconds (the part rasterised at about ``FIT_SIZE_PX``
pixels across).
"""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..camera import Camera
from ..raster import Posed, rasterize

#: the share of the silhouette's pixels the fit may leave out as not the part's surface
TRIM = 0.3
#: a silhouette of fewer pixels gives no fit
MIN_PIXELS = 50
#: the image and the camera are scaled down so that the part spans at most this many pixels:
#: shading varies slowly, and a part filling the image rasterised whole took 100-200 ms
FIT_SIZE_PX = 96.0


def sh_basis(normals: np.ndarray) -> np.ndarray:
    """(N, 9) the real spherical harmonics up to order 2 at unit normals (N, 3), constant
    factors dropped (the fit absorbs them)."""
    x, y, z = normals.T
    return np.stack([np.ones_like(x), x, y, z, x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1], axis=1)


def shading_fit(grey: np.ndarray, surface, R: np.ndarray, t: np.ndarray, camera: Camera) -> float:
    """R^2 of the spherical-harmonic fit of ``grey`` (H, W) over the silhouette of ``surface``
    (``AspectGraph.surface``) at pose R, t: fitted, the worst ``TRIM`` of the pixels left
    out, fitted again on the rest. 0, nothing explained, where the pose puts a vertex behind the
    camera, the silhouette has fewer than ``MIN_PIXELS`` pixels or the kept grey levels are flat. The image
    is first scaled down so that the part spans about ``FIT_SIZE_PX`` pixels."""
    points = surface.vertices @ R.T + t
    if np.any(points[:, 2] <= 1e-4):
        return 0.0
    size = camera.focal * np.linalg.norm(np.ptp(points, axis=0)) / float(np.mean(points[:, 2]))
    scale = min(1.0, FIT_SIZE_PX / max(size, 1e-9))
    if scale < 1.0:
        width, height = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
        sx, sy = width / camera.width, height / camera.height
        # pixel centres at integer coordinates: the scaled image's centre c' = (c + 0.5) s - 0.5
        camera = dataclasses.replace(camera, fx=camera.fx * sx, fy=camera.fy * sy, cx=(camera.cx + 0.5) * sx - 0.5,
                                     cy=(camera.cy + 0.5) * sy - 0.5, width=width, height=height)
        grey = cv2.resize(grey, (width, height), interpolation=cv2.INTER_AREA)
    raster = rasterize(camera, [Posed(surface, R, t)])
    if len(raster.pixels) < MIN_PIXELS:
        return 0.0
    basis, values = sh_basis(raster.facing_normals()), grey.reshape(-1)[raster.pixels].astype(np.float64)
    kept = np.ones(len(values), bool)
    for _ in range(2):
        # OpenCV's normal equations, solved by SVD (the least-norm fit where the normals span
        # less than the basis, a flat face), and numpy's loops rather than BLAS: OpenBLAS's
        # threads spin after a call and took 10 ms from the next image's edges on two cores
        coefficients = cv2.solve(basis[kept], values[kept], flags=cv2.DECOMP_NORMAL | cv2.DECOMP_SVD)[1].ravel()
        residual = np.abs(np.einsum("ij,j->i", basis, coefficients) - values)
        kept = residual <= np.quantile(residual, 1.0 - TRIM)
    spread = np.var(values[kept])
    return float(1.0 - np.mean(residual[kept] ** 2) / spread) if spread > 1e-9 else 0.0
