"""Pinhole camera intrinsics and the camera.json file of ../shared/CONVENTIONS.md."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

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
        """Pixel coordinates of camera-frame points (no distortion; use cv2 for that)."""
        p = np.asarray(points_cam, dtype=float)
        return np.stack([self.fx * p[..., 0] / p[..., 2] + self.cx,
                         self.fy * p[..., 1] / p[..., 2] + self.cy], axis=-1)

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
