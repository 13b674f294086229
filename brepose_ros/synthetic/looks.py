"""The "varied" look of generated scenes: random lights, gloss, backgrounds and camera blur,
so that an estimator cannot be tuned to one rendering (issue 11).

Every draw comes from the image's own generator, so a look is fixed by (seed, image index)
like the rest of the scene. ``Look.describe`` is what gt.json records of it.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import normalize
from .render import Lighting, Material

#: Background kinds: flat, blotchy (the plain look's bench), grained (brushed or blasted
#: metal, fabric), gridded (pegboard, tiles, a bin's ribs: straight edges that compete).
BACKGROUNDS = ("flat", "blotches", "grain", "grid")


@dataclass(frozen=True)
class Look:
    """Lights, the part's surface and the camera's blur and noise for one image."""

    lighting: Lighting
    material: Material
    blur: float  # Gaussian sigma, pixels
    motion: float  # length of a straight motion blur, pixels (0: none)
    motion_angle: float  # its direction, radians
    noise: float  # Gaussian sigma, grey levels
    background: str

    def describe(self) -> dict:
        key = normalize(np.asarray(self.lighting.directions[0], dtype=float))
        return {"key_light_deg": round(float(np.degrees(np.arccos(-key[2]))), 1),
                "key_light": round(self.lighting.intensities[0], 3),
                "specular": round(self.material.specular, 3), "shininess": round(self.material.shininess, 1),
                "albedo": round(float(np.mean(self.material.color)), 3), "blur": round(self.blur, 2),
                "motion": round(self.motion, 1), "noise": round(self.noise, 2), "background": self.background}


def random_look(rng: np.random.Generator, blur: float, noise: float, color: bool) -> Look:
    """Key light anywhere within 70 degrees of the optical axis, 0.4-1.2 strong, a weaker fill
    light, ambient 0.03-0.25; a grey (or tinted) part from dull to glossy; blur and noise
    scaled from the configured ones by 0.5-3.3 and 0.5-3 (zero stays zero), a motion blur in
    a quarter of the images."""
    lights = []
    for max_angle in (70.0, 85.0):
        tilt, azimuth = np.radians(rng.uniform(0.0, max_angle)), rng.uniform(0.0, 2.0 * np.pi)
        lights.append((float(np.sin(tilt) * np.cos(azimuth)), float(np.sin(tilt) * np.sin(azimuth)),
                       float(-np.cos(tilt))))
    lighting = Lighting(tuple(lights), (float(rng.uniform(0.4, 1.2)), float(rng.uniform(0.0, 0.4))),
                        float(rng.uniform(0.03, 0.25)))
    grey = rng.uniform(0.3, 0.9)
    tint = rng.uniform(0.75, 1.25, 3) if color and rng.random() < 0.3 else np.ones(3)  # anodised
    material = Material(tuple(float(c) for c in np.clip(grey * tint, 0.0, 1.0)),
                        float(rng.uniform(0.05, 1.0)), float(rng.uniform(5.0, 120.0)))
    motion = float(rng.uniform(3.0, 9.0)) if rng.random() < 0.25 else 0.0
    return Look(lighting, material, blur * float(rng.uniform(0.5, 3.3)), motion,
                float(rng.uniform(0.0, np.pi)), noise * float(rng.uniform(0.5, 3.0)),
                str(rng.choice(BACKGROUNDS)))


def background(rng: np.random.Generator, width: int, height: int, kind: str, color: bool,
               blotches) -> np.ndarray:
    """An 8-bit background of ``kind`` (``BACKGROUNDS``) under a linear or radial light
    falloff, from dark to bright. ``blotches`` draws the plain look's bench (its function)."""
    if kind == "blotches":
        return blotches(rng)
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    if rng.random() < 0.5:
        angle = rng.uniform(0.0, 2.0 * np.pi)
        falloff = np.cos(angle) * xx + np.sin(angle) * yy
    else:
        cx, cy = rng.uniform(0.0, 1.0, 2)
        falloff = -((xx - cx) ** 2 + (yy - cy) ** 2)
    grey = rng.uniform(25.0, 200.0) + rng.uniform(0.0, 70.0) * falloff / max(np.ptp(falloff), 1e-9)
    if kind == "grain":  # noise smeared along one direction, e.g. brushed metal
        streaks = cv2.GaussianBlur(rng.normal(size=(height, width)), (0, 0),
                                   sigmaX=rng.uniform(3.0, 15.0), sigmaY=rng.uniform(0.5, 1.2))
        turn = cv2.getRotationMatrix2D((width / 2, height / 2), rng.uniform(0.0, 180.0), 1.0)
        streaks = cv2.warpAffine(streaks, turn, (width, height), borderMode=cv2.BORDER_REFLECT)
        grey = grey + rng.uniform(4.0, 12.0) * streaks / max(streaks.std(), 1e-9)
    elif kind == "grid":  # lines every 15-60 px, one or two directions
        period, thickness = rng.uniform(15.0, 60.0), rng.uniform(1.0, 4.0)
        contrast = rng.uniform(10.0, 45.0) * rng.choice([-1.0, 1.0])
        angle = rng.uniform(0.0, np.pi)
        pixels = np.mgrid[0:height, 0:width]
        for turn in ((0.0, np.pi / 2) if rng.random() < 0.5 else (0.0,)):
            across = np.cos(angle + turn) * pixels[1] + np.sin(angle + turn) * pixels[0]
            grey = grey + contrast * (np.mod(across, period) < thickness)
    grey = grey + rng.uniform(1.0, 5.0) * cv2.GaussianBlur(rng.normal(size=(height, width)), (0, 0), 1.0)
    image = grey[..., None] * rng.uniform(0.85, 1.15, 3) if color else grey
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def camera_effects(rng: np.random.Generator, image: np.ndarray, blur: float, noise: float,
                   motion: float = 0.0, motion_angle: float = 0.0) -> np.ndarray:
    """A straight motion blur ``motion`` pixels long, a Gaussian blur, then sensor noise
    (Gaussian, sigma ``noise`` grey levels) on a float image."""
    if motion > 0:
        size = int(np.ceil(motion)) | 1
        kernel = np.zeros((size, size))
        half = (size - 1) / 2
        d = np.array([np.cos(motion_angle), np.sin(motion_angle)]) * motion / 2
        cv2.line(kernel, tuple(np.rint([half - d[0], half - d[1]]).astype(int)),
                 tuple(np.rint([half + d[0], half + d[1]]).astype(int)), 1.0, 1)
        image = cv2.filter2D(image, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)
    if blur > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur)
    if noise > 0:
        image = image + rng.normal(0.0, noise, image.shape)
    return image
