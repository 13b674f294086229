"""Small rigid-body helpers shared by every stage (no ROS, no OpenCascade).

Frames follow ../shared/CONVENTIONS.md: the camera is the OpenCV optical frame (x right,
y down, z forward) and a pose is T_cam_model with ``X_cam = R @ X_model + t``.
"""
from __future__ import annotations

import numpy as np


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vector(s) along the last axis."""
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def unit_rows(v: np.ndarray, fallback) -> np.ndarray:
    """``normalize`` of each row, ``fallback`` for a row of no length (which has no direction)."""
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(length > 0, v / np.where(length > 0, length, 1.0), fallback)


def default_up(direction: np.ndarray) -> np.ndarray:
    """An up vector not parallel to ``direction``: model +Z, or +Y near the poles."""
    direction = normalize(direction)
    up = np.array([0.0, 0.0, 1.0])
    if abs(direction @ up) > 0.99:
        up = np.array([0.0, 1.0, 0.0])
    return up


def look_at_rotation(view_direction: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """R_cam_model of a camera looking along ``view_direction`` (model frame).

    The camera z axis is the viewing direction; its y axis (image down) is opposite to the
    part of ``up`` orthogonal to the viewing direction, so model "up" appears up in the image.
    """
    z = normalize(view_direction)
    if up is None:
        up = default_up(z)
    up = np.asarray(up, dtype=float)
    y = -(up - (up @ z) * z)
    y = normalize(y)
    x = np.cross(y, z)
    return np.stack([x, y, z])


def direction_to(point: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Unit direction, in the model frame, from the camera of pose (R, t) to a model point:
    the direction the camera sees that point from (camera centre is -R^T t)."""
    return normalize(np.asarray(point) + np.asarray(R).T @ np.asarray(t))


def rot_z(angle: float) -> np.ndarray:
    """Rotation about the camera's optical axis: an in-plane rotation of the image."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: the rotation by ``angle`` (radians) about the unit ``axis``."""
    x, y, z = axis
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def turned_poses(R: np.ndarray, t: np.ndarray, S: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The poses (K, 3, 3), (K, 3) that show the model turned by X -> S[k] X + b[k] where pose
    R, t shows it unturned: R S^T, t - R S^T b."""
    R_turned = R @ S.transpose(0, 2, 1)
    return R_turned, t - np.einsum("kij,kj->ki", R_turned, b)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    a, b = normalize(a), normalize(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:
        axis = normalize(np.cross(a, [1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 1.0, 0.0]))
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotations, in degrees (CONVENTIONS.md rotation error)."""
    cos = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, w >= 0."""
    R = np.asarray(R, dtype=float)
    m = R
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a quaternion (x, y, z, w)."""
    x, y, z, w = normalize(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation drawn uniformly from SO(3)."""
    q = rng.normal(size=4)
    return matrix_from_quaternion(q)
