"""Synthetic test scenes with exact ground truth, written as scene folders (``scene_folder``).

A scene folder holds camera.json, model.step, images/NNNNNN.png and gt.json; the generator also writes the part's visible mask to
masks/NNNNNN.png. Occlusion and clutter follow the seed paper's section 7.2: occluders
(bars and pipes) in front of the part hide a requested share of it, other shapes lie
behind it, and the share actually hidden is measured from the masks and recorded.

Two looks: "plain" renders every image under the same two lights with a grey part on a
blotchy grey bench, bars and pipes as props; "varied" (``looks.py``) draws the lights, the
part's gloss and grey, the background (flat, blotchy, grained or gridded), blur and noise per
image, and its props also include blobs, polygon plates, glued blocks and other parts.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
from tqdm import tqdm

from ..camera import Camera
from ..geometry import look_at_rotation, normalize, random_rotation, rot_z
from ..offline.cad import Mesh, load_step, tessellate
from ..scene_folder import GroundTruth, Scene, SceneError
from .looks import Look, background, camera_effects, random_look
from .props import COMPACT, ELONGATED, KINDS, box_mesh, cylinder_mesh, stretched, unit_prop
from .render import Lighting, Material, Placed, rasterize, render

__all__ = ["LOOKS", "SceneConfig", "box_mesh", "cylinder_mesh", "generate_scene"]

#: "plain": the fixed look of the first sessions; "varied": ``looks.random_look`` per image.
LOOKS = ("plain", "varied")


@dataclass(frozen=True)
class SceneConfig:
    """What a generated scene looks like. Shares are of the image's smaller side."""

    width: int = 640
    height: int = 480
    fx: float = 600.0
    span: tuple[float, float] = (0.25, 0.60)  # part's projected size, random in this range
    elevation: tuple[float, float] | None = None  # degrees above the model XY plane; None: any
    offcenter: bool = False  # part anywhere in the central 80 % instead of centred
    occlusion: float = 0.0  # share of the part's silhouette to hide behind an occluder
    clutter: int = 0  # number of shapes behind the part
    noise: float = 2.0  # Gaussian noise sigma, grey levels
    blur: float = 0.6  # Gaussian blur sigma, pixels
    color: bool = False  # BGR images instead of grey
    look: str = "plain"  # LOOKS; "varied" scales noise and blur by a random factor per image

    def __post_init__(self):
        lo, hi = self.span
        if not 0.0 < lo <= hi <= 0.9:
            raise SceneError(f"span must satisfy 0 < min <= max <= 0.9, got {lo}, {hi}")
        if not 0.0 <= self.occlusion <= 0.5:
            raise SceneError(f"occlusion must be within [0, 0.5], got {self.occlusion}")
        if self.clutter < 0 or self.noise < 0 or self.blur < 0:
            raise SceneError("clutter, noise and blur must not be negative")
        if self.elevation is not None and not -90 <= self.elevation[0] <= self.elevation[1] <= 90:
            raise SceneError(f"elevation band must satisfy -90 <= min <= max <= 90, got {self.elevation}")
        if self.look not in LOOKS:
            raise SceneError(f"look must be one of {', '.join(LOOKS)}, got {self.look!r}")

    def camera(self) -> Camera:
        return Camera.from_fov(self.width, self.height, self.fx)


def generate_scene(step: str | Path, folder: str | Path, n: int, seed: int = 0,
                   config: SceneConfig = SceneConfig(), progress: bool = False,
                   distractors: Sequence[Mesh] = ()) -> Scene:
    """Render ``n`` images of the part in a STEP file into a new scene folder.

    Image i depends only on (seed, i) (and the ``distractors``: meshes of other parts that the
    varied look may use as occluders and clutter), so a scene can be regrown or extended exactly.
    """
    folder = Path(folder)
    if n < 1:
        raise SceneError(f"a scene needs at least one image, got n={n}")
    if folder.exists() and any(folder.iterdir()):
        raise SceneError(f"{folder} exists and is not empty; choose a new folder")
    part = load_step(step)
    mesh = tessellate(part)
    camera = config.camera()
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "masks").mkdir(exist_ok=True)
    camera.save(folder / "camera.json")
    shutil.copyfile(step, folder / "model.step")
    records, entries = [], []
    for i in tqdm(range(n), desc="rendering", disable=not progress):
        image, mask, R, t, visible, look = render_image(mesh, part.center, config, seed, i, distractors)
        name = f"images/{i:06d}.png"
        cv2.imwrite(str(folder / name), image)
        cv2.imwrite(str(folder / f"masks/{i:06d}.png"), mask.astype(np.uint8) * 255)
        gt = GroundTruth(name, folder / name, R, t, visible, 1.0 - visible, config.clutter)
        record = {"image": name, "R": R.reshape(-1).tolist(), "t": t.tolist(),
                  "visible_fraction": gt.visible_fraction, "occlusion": gt.occlusion,
                  "clutter": gt.clutter}
        records.append(record | ({"look": look} if look else {}))
        entries.append(gt)
    # One entry per line: readable and diffable, full float precision.
    (folder / "gt.json").write_text("[\n" + ",\n".join(json.dumps(r) for r in records) + "\n]\n")
    return Scene(folder, camera, folder / "model.step", entries)


def render_image(mesh: Mesh, center: np.ndarray, config: SceneConfig, seed: int, index: int,
                 distractors: Sequence[Mesh] = (), change_look: Callable[[Look], Look] | None = None):
    """Image ``index`` of the scene of ``seed`` as :func:`generate_scene` renders it: the noisy
    image, the part's visible mask, its pose, its visible share and what the varied look drew
    (an empty dict for the plain look). ``change_look`` alters the varied look after it is
    drawn: the pose, lights, props and noise stay those of the scene, so one look factor
    (e.g. the motion blur, bench/motion_pairs.py) can be tested on the very same image."""
    rng, camera, distractors = np.random.default_rng([seed, index]), config.camera(), tuple(distractors)
    R, t = _sample_pose(rng, mesh, center, camera, config)
    varied = config.look == "varied"
    look = random_look(rng, config.blur, config.noise, config.color) if varied else None
    if varied and change_look is not None:
        look = change_look(look)
    kinds = (KINDS + ("part",) * bool(distractors)) if varied else PROPS
    part = Placed(mesh, R, t, look.material) if varied else Placed(mesh, R, t)
    alone = rasterize(camera, [part])
    full = alone.labels == 0
    objects = [part]
    record = look.describe() if varied else {}
    if config.occlusion > 0:
        occluder, kind = _occluder(rng, camera, alone.depth, config.occlusion, config.color, kinds,
                                   distractors)
        objects.append(occluder)
        if varied:
            record["occluder"] = kind
    objects += _clutter(rng, camera, alone.depth, config.clutter, config.color, kinds, distractors,
                        wide=varied)
    if varied:
        scenery = background(rng, camera.width, camera.height, look.background, config.color,
                             lambda generator: _background(generator, camera, config.color))
    else:
        scenery = _background(rng, camera, config.color)
    result = render(camera, objects, scenery, color=config.color,
                    lighting=look.lighting if varied else Lighting())
    image = result.image.astype(float)
    if varied:
        image = camera_effects(rng, image, look.blur, look.noise, look.motion, look.motion_angle)
    else:
        image = camera_effects(rng, image, config.blur, config.noise)
    image = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    return image, result.mask, R, t, float(result.mask.sum() / full.sum()), record


def _projected_box(mesh: Mesh, R: np.ndarray, t: np.ndarray, camera: Camera) -> np.ndarray:
    """(u_min, v_min, u_max, v_max) of the projected vertices."""
    uv = camera.project(mesh.vertices @ R.T + t)
    return np.concatenate([uv.min(axis=0), uv.max(axis=0)])


def _sample_pose(rng, mesh, center, camera, config) -> tuple[np.ndarray, np.ndarray]:
    """A viewpoint on the sphere (or elevation band), in-plane rotation, distance, offset."""
    if config.elevation is None:
        towards_camera = normalize(rng.normal(size=3))
    else:
        lo, hi = np.radians(config.elevation)
        elevation = np.arcsin(rng.uniform(np.sin(lo), np.sin(hi)))  # uniform in area
        azimuth = rng.uniform(0.0, 2.0 * np.pi)
        towards_camera = np.array([np.cos(elevation) * np.cos(azimuth),
                                   np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    R = rot_z(rng.uniform(0.0, 2.0 * np.pi)) @ look_at_rotation(-towards_camera)
    side = min(camera.width, camera.height)
    span = rng.uniform(*config.span)
    # The projected size is nearly proportional to 1/distance: a few fixed-point steps.
    extent = np.ptp((mesh.vertices - center) @ R[:2].T, axis=0).max()
    distance = camera.fx * extent / (span * side) + extent
    for _ in range(4):
        box = _projected_box(mesh, R, np.array([0.0, 0.0, distance]) - R @ center, camera)
        distance *= (box[2:] - box[:2]).max() / (span * side)
    t = np.array([0.0, 0.0, distance]) - R @ center
    if not config.offcenter:
        return R, t
    box = _projected_box(mesh, R, t, camera)
    size = np.array([camera.width, camera.height])
    low, high = 0.1 * size - box[:2], 0.9 * size - 1 - box[2:]
    shift = rng.uniform(low, high) if (low <= high).all() else np.zeros(2)
    for _ in range(10):  # perspective changes the box a little when the part moves aside
        moved = t + distance * np.array([shift[0] / camera.fx, shift[1] / camera.fy, 0.0])
        box = _projected_box(mesh, R, moved, camera)
        if (box[:2] >= 0.1 * size).all() and (box[2:] <= 0.9 * size - 1).all():
            return R, moved
        shift *= 0.7
    return R, t


def _unit_pixel_ray(camera: Camera, pixel: np.ndarray) -> np.ndarray:
    return np.array([(pixel[0] - camera.cx) / camera.fx, (pixel[1] - camera.cy) / camera.fy, 1.0])


def _scaled(mesh: Mesh, factor: float) -> Mesh:
    return Mesh(mesh.vertices * factor, mesh.triangles, mesh.normals)


#: The plain look's props.
PROPS = ("pipe", "bar")


def _sized(kind: str, unit: Mesh, length: float, width: float) -> Mesh:
    """An elongated prop ``length`` long and ``width`` thick, or a compact one ``width`` across
    its y axis (the occluder's side across the direction it slides)."""
    if kind in ELONGATED:
        return stretched(unit, (length, width, width))
    return stretched(unit, width / max(np.ptp(unit.vertices[:, 1]), 0.05))


def _at_depth(mesh: Mesh, R: np.ndarray, pixel: np.ndarray, depth: float, camera: Camera,
              material: Material) -> Placed:
    """Place a depth-1-sized mesh centred on ``pixel`` at ``depth``: scaling by the depth
    keeps its image size, a pinhole camera's similar triangles."""
    return Placed(_scaled(mesh, depth), R, depth * _unit_pixel_ray(camera, pixel), material)


def _random_material(rng: np.random.Generator, color: bool) -> Material:
    grey = rng.uniform(0.25, 0.8)
    tint = rng.uniform(0.8, 1.2, 3) if color else np.ones(3)
    return Material(tuple(np.clip(grey * tint, 0.0, 1.0)), rng.uniform(0.05, 0.4), rng.uniform(8, 40))


def _occluder(rng: np.random.Generator, camera: Camera, part_depth: np.ndarray, target: float,
              color: bool, kinds: tuple[str, ...], distractors: tuple[Mesh, ...]) -> tuple[Placed, str]:
    """A prop of one of ``kinds`` in front of the part, slid across it until it hides ``target``
    of it; returns it and its kind.

    The occluder crosses the part broadside from a random direction; the hidden share
    shrinks as it slides out, so a bisection on the offset meets the target closely. Trial
    placements are rasterised only over the part's bounding box (a camera cropped to it by
    shifting the principal point, which is exact).
    """
    full = np.isfinite(part_depth)
    n_full = full.sum()
    ys, xs = np.nonzero(full)
    x0, y0 = xs.min(), ys.min()
    crop = Camera(camera.fx, camera.fy, camera.cx - x0, camera.cy - y0, int(xs.max() - x0 + 1),
                  int(ys.max() - y0 + 1), camera.distortion)
    crop_depth = part_depth[y0:y0 + crop.height, x0:x0 + crop.width]
    center = np.array([xs.mean(), ys.mean()])
    size = max(np.ptp(xs), np.ptp(ys)) + 1.0
    z_near = part_depth[full].min()
    angle = rng.uniform(0.0, 2.0 * np.pi)
    slide = np.array([np.cos(angle), np.sin(angle)])
    roll = rng.uniform(0.0, np.pi)
    material = _random_material(rng, color)
    kind = str(rng.choice(kinds))
    width = rng.uniform(0.25, 0.45) * size
    if kind in COMPACT + ("part",):
        roll = (roll - np.pi / 2) / 2  # within 45 degrees of facing the camera: plates stay wide
    shape = unit_prop(kind, rng, distractors)
    R = rot_z(angle + np.pi / 2) @ cv2.Rodrigues(np.array([roll, 0.0, 0.0]))[0]  # long axis across the slide

    def place(offset, unit):
        # Keep the whole occluder in front of the part's nearest point.
        depth = 0.9 * z_near / (1.0 + (unit.vertices @ R.T)[:, 2].max())
        return _at_depth(unit, R, center + offset * slide, depth, camera, material)

    def hidden(occluder):
        depth = rasterize(crop, [occluder]).depth
        return (np.isfinite(crop_depth) & (depth < crop_depth)).sum() / n_full

    while True:
        unit = _sized(kind, shape, 2.0 * size / camera.fx, width / camera.fx)
        if hidden(place(0.0, unit)) >= target or width > 2.0 * size:
            break
        width *= 1.4
    best, best_error = place(0.0, unit), np.inf
    low, high = 0.0, size + width
    for _ in range(14):
        offset = (low + high) / 2.0
        candidate = place(offset, unit)
        share = hidden(candidate)
        if abs(share - target) < best_error:
            best, best_error = candidate, abs(share - target)
        if best_error < 2e-3:
            break
        low, high = (offset, high) if share > target else (low, offset)
    return best, kind


def _clutter(rng: np.random.Generator, camera: Camera, part_depth: np.ndarray, count: int,
             color: bool, kinds: tuple[str, ...], distractors: tuple[Mesh, ...],
             wide: bool = False) -> list[Placed]:
    """Props of ``kinds`` anywhere in the image but entirely behind the part, 0.3-1 times its
    size (``wide``: 0.2-1.2 times)."""
    full = np.isfinite(part_depth)
    ys, xs = np.nonzero(full)
    size = max(np.ptp(xs), np.ptp(ys)) + 1.0
    z_far = part_depth[full].max()
    props = []
    for _ in range(count):
        # At most fx pixels long, so the prop is at most 1 long at depth 1 and fits behind.
        length = min(rng.uniform(*((0.2, 1.2) if wide else (0.3, 1.0))) * size, camera.fx) / camera.fx
        kind = str(rng.choice(kinds))
        thickness = rng.uniform(0.1, 0.5) * length
        shape = unit_prop(kind, rng, distractors)
        unit = stretched(shape, length) if kind not in ELONGATED else _sized(kind, shape, length, thickness)
        R = random_rotation(rng)
        nearest = 1.0 + (unit.vertices @ R.T)[:, 2].min()  # > 0.13 by the size bounds
        depth = z_far * rng.uniform(1.05, 1.6) / nearest
        pixel = rng.uniform([0.0, 0.0], [camera.width - 1.0, camera.height - 1.0])
        props.append(_at_depth(unit, R, pixel, depth, camera, _random_material(rng, color)))
    return props


def _background(rng: np.random.Generator, camera: Camera, color: bool) -> np.ndarray:
    """A grey workbench: a linear gradient, soft blotches and fine grain."""
    h, w = camera.height, camera.width
    yy, xx = np.mgrid[0:h, 0:w]
    angle = rng.uniform(0.0, 2.0 * np.pi)
    ramp = (np.cos(angle) * xx + np.sin(angle) * yy) / max(h, w)
    grey = rng.uniform(60.0, 130.0) + rng.uniform(10.0, 40.0) * ramp
    grey += 6.0 * cv2.resize(rng.normal(size=(6, 8)), (w, h), interpolation=cv2.INTER_CUBIC)
    grey += 4.0 * cv2.GaussianBlur(rng.normal(size=(h, w)), (0, 0), 1.5)
    image = grey[..., None] * (rng.uniform(0.92, 1.08, 3) if color else np.ones(1))
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
