"""CPU renderer for synthetic images with exact ground truth: the z-buffer of
``brepose_ros.raster`` (pixel centres and projection as every other stage's), shaded.

Shading imitates a texture-less machined part: Lambertian diffuse light from two directional
lights close to the optical axis plus a Blinn-Phong highlight. Normals are interpolated within
a face and split across B-Rep edges (see ``cad.tessellate``), so faces meeting at an edge get
different brightness: the edges are what the pose estimator looks for.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np

from ..camera import Camera
from ..geometry import normalize
from ..raster import Posed, Raster, rasterize

__all__ = ["Lighting", "Material", "METAL", "Placed", "Raster", "Rendering", "rasterize", "render", "shade"]


@dataclass(frozen=True)
class Material:
    """Surface reflectance: BGR albedo in [0, 1] and a white Blinn-Phong highlight."""

    color: tuple[float, float, float] = (0.62, 0.62, 0.64)
    specular: float = 0.3
    shininess: float = 30.0


#: Bare machined aluminium / steel: light grey, moderately glossy.
METAL = Material()


@dataclass(frozen=True)
class Lighting:
    """Directional lights in the camera frame, pointing from the scene towards the light.

    The key light sits a little up-left of the camera, the fill light down-right, so two
    faces seen at the same angle still differ in brightness.
    """

    directions: tuple[tuple[float, float, float], ...] = ((-0.35, -0.5, -1.0), (0.45, 0.25, -1.0))
    intensities: tuple[float, ...] = (0.75, 0.3)
    ambient: float = 0.12


@dataclass
class Placed(Posed):
    """A mesh at a pose, with its material."""

    material: Material = METAL


@dataclass
class Rendering:
    """A rendered image with its ground truth.

    ``image`` is 8-bit grey (H, W) or BGR (H, W, 3); ``mask`` the visible pixels of the
    first object (the part); ``depth`` and ``labels`` as in ``Raster``.
    """

    image: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    labels: np.ndarray = field(repr=False)


def shade(raster: Raster, objects: Sequence[Placed], lighting: Lighting = Lighting()) -> np.ndarray:
    """BGR radiance in [0, 1] of the visible pixels (one row per ``raster.pixels``)."""
    view = -normalize(raster.points)
    n = raster.facing_normals()
    labels = raster.labels.reshape(-1)[raster.pixels]
    albedo = np.array([obj.material.color for obj in objects])[labels]
    specular = np.array([obj.material.specular for obj in objects])[labels]
    shininess = np.array([obj.material.shininess for obj in objects])[labels]
    diffuse = np.full(len(n), lighting.ambient)
    highlight = np.zeros(len(n))
    for direction, power in zip(lighting.directions, lighting.intensities):
        light = normalize(np.asarray(direction, dtype=float))
        diffuse += power * np.clip(n @ light, 0.0, None)
        half = normalize(view + light)
        highlight += power * np.clip(np.einsum("ij,ij->i", n, half), 0.0, None) ** shininess
    return albedo * diffuse[:, None] + (specular * highlight)[:, None]


def render(camera: Camera, objects: Sequence[Placed], background: np.ndarray | float = 0.0,
           color: bool = False, lighting: Lighting = Lighting()) -> Rendering:
    """Render objects (the first one is the part whose mask is returned) over a background.

    ``background`` is an 8-bit grey or BGR image of the camera's size, or one grey level.
    """
    h, w = camera.height, camera.width
    raster = rasterize(camera, objects)
    canvas = np.empty((h, w, 3))
    canvas[:] = (np.asarray(background, dtype=float).reshape(h, w, -1) if np.ndim(background)
                 else float(background))
    flat = canvas.reshape(-1, 3)
    flat[raster.pixels] = 255.0 * shade(raster, objects, lighting)
    bgr = np.clip(np.rint(canvas), 0, 255).astype(np.uint8)
    image = bgr if color else cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    return Rendering(image, raster.labels == 0, raster.depth, raster.labels)
