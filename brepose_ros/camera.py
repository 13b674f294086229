"""Pinhole camera intrinsics, the camera.json file of ../shared/CONVENTIONS.md, and the
projections between model points, pixels and normalised camera coordinates.

Normalised camera coordinates are ((u - cx) / fx, (v - cy) / fy) of the undistorted
pixel: the online stages match and refine there, where a pose projects by a plain
division, and go back to pixels (with distortion) only to look at the image.

The virtual camera: an off-centre part is seen along the ray through it, not along the
optical axis. Turning the rays so that this ray becomes the optical axis (``R_align``, a
pure rotation of the rays, exact for a pinhole camera) shows the part centred, as the
orthographic views of the aspect graph see it.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np


class CameraError(ValueError):
    """Intrinsics that are missing, malformed or physically impossible."""


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels with optional plumb_bob distortion [k1, k2, p1, p2, k3]."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = field(default=())

    def __post_init__(self):
        values = [self.fx, self.fy, self.cx, self.cy]
        if not all(np.isfinite(values)):
            raise CameraError(f"camera intrinsics must be finite, got fx, fy, cx, cy = {values}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"image size must be positive, got {self.width}x{self.height}")
        if len(self.distortion) not in (0, 4, 5, 8):
            raise CameraError(f"distortion must have 0, 4, 5 or 8 coefficients, got {len(self.distortion)}")

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.distortion if self.distortion else np.zeros(5), dtype=float)

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.distortion)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel coordinates of camera-frame points, without distortion (``project_model``
        applies it)."""
        p = np.asarray(points_cam, dtype=float)
        return np.stack([self.fx * p[..., 0] / p[..., 2] + self.cx,
                         self.fy * p[..., 1] / p[..., 2] + self.cy], axis=-1)

    def project_model(self, points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Pixel coordinates, with the camera's distortion, of model points (..., 3) seen
        with pose (R, t); the shape is kept."""
        pts = np.asarray(points, dtype=float)
        flat = pts.reshape(-1, 3)
        if len(flat) == 0:
            return np.zeros(pts.shape[:-1] + (2,))
        rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=float))
        out, _ = cv2.projectPoints(flat, rvec, np.asarray(t, dtype=float), self.K, self.dist_coeffs)
        return out.reshape(pts.shape[:-1] + (2,))

    def undistort(self, points_px: np.ndarray) -> np.ndarray:
        """Pixels (..., 2), e.g. segments (N, 2, 2), in normalised camera coordinates; the
        shape is kept."""
        pts = np.asarray(points_px, dtype=float)
        flat = pts.reshape(-1, 1, 2)
        if len(flat) == 0:
            return np.zeros(pts.shape)
        if self.has_distortion:
            return cv2.undistortPoints(flat, self.K, self.dist_coeffs).reshape(pts.shape)
        return ((flat.reshape(-1, 2) - [self.cx, self.cy]) / [self.fx, self.fy]).reshape(pts.shape)

    @property
    def focal(self) -> float:
        """The mean focal length: pixels per normalised unit, for tolerances given in pixels."""
        return (self.fx + self.fy) / 2.0

    def to_dict(self) -> dict:
        d = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
             "width": self.width, "height": self.height}
        if self.distortion:
            d["distortion"] = list(self.distortion)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in d]
        if missing:
            raise CameraError(f"camera description lacks {', '.join(missing)}")
        try:
            return cls(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                       int(d["width"]), int(d["height"]),
                       tuple(float(x) for x in d.get("distortion") or ()))
        except (TypeError, ValueError) as exc:
            if isinstance(exc, CameraError):
                raise
            raise CameraError(f"camera description has a non-numeric value: {exc}") from exc

    @classmethod
    def load(cls, path: str | Path) -> "Camera":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise CameraError(f"camera file {path} does not exist") from None
        except json.JSONDecodeError as exc:
            raise CameraError(f"camera file {path} is not valid JSON: {exc}") from None
        if not isinstance(data, dict):
            raise CameraError(f"camera file {path} must hold a JSON object")
        return cls.from_dict(data)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_fov(cls, width: int, height: int, fx: float) -> "Camera":
        """A distortion-free camera with square pixels and the principal point at the centre."""
        return cls(fx, fx, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def project_normalised(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Normalised camera coordinates of model points (..., 3) seen with pose (R, t); a
    point behind the camera divides by 1e-9 rather than by its depth."""
    cam = np.asarray(points) @ R.T + t
    return cam[..., :2] / np.maximum(cam[..., 2:3], 1e-9)


def virtual_alignment(center_normalised: np.ndarray) -> np.ndarray:
    """R_align: turns the virtual camera's optical axis onto the ray through the centre.

    ``geometry.rotation_between`` from the optical axis, its steps on the 3-vectors done on
    Python floats, in the same operations and order (the same bits, signed zeros included):
    its numpy calls on 3-vectors cost ~45 us a call, and the search makes one per seed. The
    product ``vx @ vx`` stays numpy's (the BLAS one, fused multiply-adds where the machine
    has them), so it rounds as ``rotation_between``'s does."""
    x, y = float(center_normalised[0]), float(center_normalised[1])
    norm = math.sqrt(x * x + y * y + 1.0)
    bx, by, bz = x / norm, y / norm, 1.0 / norm
    # the cross product v = (0, 0, 1) x b term by term as np.cross forms it, and its matrix
    v0, v1, v2 = 0.0 * bz - 1.0 * by, 1.0 * bx - 0.0 * bz, 0.0 * by - 0.0 * bx
    skew = np.array([[0.0, -v2, v1], [v2, 0.0, -v0], [-v1, v0, 0.0]])
    return np.eye(3) + skew + skew @ skew / (1.0 + bz)


def to_virtual(normalised: np.ndarray, R_align: np.ndarray) -> np.ndarray:
    """Points (..., 2), e.g. segments (N, 2, 2), seen by the virtual camera R_align^T (rays
    rotated, then re-projected); the shape is kept."""
    normalised = np.asarray(normalised, dtype=float)
    pts = normalised.reshape(-1, 2)
    rays = np.concatenate([pts, np.ones((len(pts), 1))], axis=1) @ R_align  # R_align^T r
    return (rays[:, :2] / rays[:, 2:3]).reshape(normalised.shape)
