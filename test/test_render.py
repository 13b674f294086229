"""The renderer's ground truth is exact: silhouettes, depth and visibility."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from brepose_ros.offline.cad import load_step, tessellate
from brepose_ros.camera import Camera
from brepose_ros.geometry import look_at_rotation, random_rotation, rot_z
from brepose_ros.synthetic.render import Placed, rasterize, render
from brepose_ros.synthetic.scenes import box_mesh

CAMERA = Camera.from_fov(640, 480, 600.0)
ONE_PIXEL = np.ones((3, 3), np.uint8)


@pytest.fixture(scope="module")
def part(sample_step):
    loaded = load_step(sample_step)
    return loaded, tessellate(loaded)


def projected_silhouette(mesh, R, t, camera):
    """Every triangle filled at its cv2.projectPoints corners (sub-pixel precise)."""
    uv = cv2.projectPoints(mesh.vertices, cv2.Rodrigues(R)[0], t, camera.K, camera.dist_coeffs)[0]
    corners = np.rint(uv.reshape(-1, 2) * 256).astype(np.int32)
    reference = np.zeros((camera.height, camera.width), np.uint8)
    for tri in mesh.triangles:
        cv2.fillConvexPoly(reference, corners[tri], 1, shift=8)
    return reference.astype(bool), uv.reshape(-1, 2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_silhouette_matches_projectpoints_within_one_pixel(part, seed):
    loaded, mesh = part
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    t = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04), 0.35]) - R @ loaded.center
    mask = render(CAMERA, [Placed(mesh, R, t)]).mask
    reference, uv = projected_silhouette(mesh, R, t, CAMERA)
    grown = cv2.dilate(mask.astype(np.uint8), ONE_PIXEL).astype(bool)
    assert mask.sum() > 5000
    assert not (mask & ~cv2.dilate(reference.astype(np.uint8), ONE_PIXEL).astype(bool)).any()
    assert not (reference & ~grown).any()
    pixels = np.rint(uv).astype(int)
    assert grown[pixels[:, 1], pixels[:, 0]].all(), "a projected vertex is more than a pixel off"


def test_depth_is_perspective_correct():
    """Back-projected depth pixels lie on the faces of a tilted box (1/z interpolation)."""
    mesh = box_mesh(0.1, 0.06, 0.04)
    R = rot_z(0.4) @ look_at_rotation(np.array([0.5, -0.7, -0.6]))
    t = np.array([0.02, -0.01, 0.3])
    raster = rasterize(CAMERA, [Placed(mesh, R, t)])
    v, u = np.nonzero(np.isfinite(raster.depth))
    rays = np.linalg.inv(CAMERA.K) @ np.stack([u, v, np.ones_like(u)]).astype(float)
    points_model = (rays * raster.depth[v, u] - t[:, None]).T @ R  # R^T (X - t)
    face_distance = np.abs(np.abs(points_model) - np.array([0.05, 0.03, 0.02])).min(axis=1)
    assert face_distance.max() < 1e-9
    assert np.allclose(raster.points[:, 2], raster.depth.reshape(-1)[raster.pixels])


def test_nearest_object_wins_and_hides_the_part():
    part = Placed(box_mesh(0.1, 0.1, 0.1), np.eye(3), np.array([0.0, 0.0, 0.5]))
    occluder = Placed(box_mesh(0.03, 0.2, 0.03), np.eye(3), np.array([0.0, 0.0, 0.3]))
    alone = render(CAMERA, [part]).mask
    both = render(CAMERA, [part, occluder])
    front = both.labels == 1
    assert front.any() and not (both.mask & front).any()
    assert both.mask.sum() + (alone & front).sum() == alone.sum()
    assert np.allclose(both.depth[front], 0.285)
    assert np.isinf(both.depth[both.labels < 0]).all()


def test_faces_meeting_at_an_edge_differ_in_brightness():
    cube = box_mesh(0.05, 0.05, 0.05)
    R = look_at_rotation(np.array([-1.0, -1.0, -1.0]))  # three faces at equal angles
    rendering = render(CAMERA, [Placed(cube, R, np.array([0.0, 0.0, 0.3]))], background=50)
    raster = rasterize(CAMERA, [Placed(cube, R, np.array([0.0, 0.0, 0.3]))])
    facing = np.argmax(np.abs(raster.normals @ R), axis=1)  # which model axis each pixel faces
    image = rendering.image.reshape(-1)[raster.pixels].astype(float)
    means = sorted(image[facing == axis].mean() for axis in range(3))
    assert np.diff(means).min() > 8, means
    assert (rendering.image[~rendering.mask] == 50).all()


def test_colour_rendering_over_a_background_image():
    background = np.full((CAMERA.height, CAMERA.width, 3), (10, 20, 30), np.uint8)
    rendering = render(CAMERA, [Placed(box_mesh(0.05, 0.05, 0.05), np.eye(3), np.array([0, 0, 0.4]))],
                       background, color=True)
    assert rendering.image.shape == (480, 640, 3)
    assert (rendering.image[~rendering.mask] == (10, 20, 30)).all()
    assert rendering.image[rendering.mask].mean() > 60


def test_objects_behind_the_camera_are_not_drawn():
    rendering = render(CAMERA, [Placed(box_mesh(0.05, 0.05, 0.05), np.eye(3), np.array([0, 0, -0.4]))])
    assert not rendering.mask.any() and np.isinf(rendering.depth).all()
