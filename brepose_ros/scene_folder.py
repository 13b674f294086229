"""A scene folder (../shared/CONVENTIONS.md): camera.json, model.step, images/ and gt.json.

Synthetic scenes (``synthetic.scenes``) and real test data share it; :func:`load_scene`
checks everything the evaluator relies on.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera, CameraError


class SceneError(ValueError):
    """A scene folder or scene request that cannot be used, with the reason."""


@dataclass
class GroundTruth:
    """One gt.json entry; ``image`` is the path as written there, ``path`` the resolved file."""

    image: str
    path: Path
    R: np.ndarray
    t: np.ndarray
    visible_fraction: float | None = None
    occlusion: float | None = None
    clutter: int | None = None


@dataclass
class Scene:
    folder: Path
    camera: Camera
    step: Path
    entries: list[GroundTruth]


def load_scene(folder: str | Path) -> Scene:
    """Read a scene folder (synthetic or real), checking everything the evaluator relies on."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SceneError(f"scene folder {folder} does not exist")
    try:
        camera = Camera.load(folder / "camera.json")
    except CameraError as exc:
        raise SceneError(f"scene {folder}: {exc}") from None
    step = folder / "model.step"
    if not step.is_file():
        raise SceneError(f"scene {folder} has no model.step")
    try:
        records = json.loads((folder / "gt.json").read_text())
    except FileNotFoundError:
        raise SceneError(f"scene {folder} has no gt.json") from None
    except json.JSONDecodeError as exc:
        raise SceneError(f"{folder / 'gt.json'} is not valid JSON: {exc}") from None
    if not isinstance(records, list):
        raise SceneError(f"{folder / 'gt.json'} must hold a list of entries")
    return Scene(folder, camera, step, [_entry(folder, i, r) for i, r in enumerate(records)])


def _entry(folder: Path, index: int, record) -> GroundTruth:
    where = f"{folder / 'gt.json'} entry {index}"
    if not isinstance(record, dict) or not isinstance(record.get("image"), str):
        raise SceneError(f"{where} must be an object with an \"image\" path")
    try:
        R = np.array(record["R"], dtype=float).reshape(3, 3)
        t = np.array(record["t"], dtype=float).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise SceneError(f"{where} needs \"R\" (9 numbers) and \"t\" (3 numbers)") from None
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise SceneError(f"{where} has a non-finite pose")
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0):
        raise SceneError(f"{where}: R is not a rotation matrix")
    path = folder / record["image"]
    if not path.is_file():
        raise SceneError(f"{where}: image {path} does not exist")
    optional = {key: record.get(key) for key in ("visible_fraction", "occlusion", "clutter")}
    return GroundTruth(record["image"], path, R, t, **optional)
