"""The shading fit (online.appearance) on rendered parts with exact ground truth."""
import numpy as np

from brepose_ros.camera import Camera
from brepose_ros.geometry import rot_z, rotation_about
from brepose_ros.offline.cad import Mesh, load_step, tessellate
from brepose_ros.online.appearance import MIN_PIXELS, shading_fit
from brepose_ros.raster import Posed, rasterize
from brepose_ros.synthetic.render import Lighting, Material, Placed, render


def test_the_shading_fit_explains_a_lambertian_part_at_its_pose_and_not_at_another(builtin_step):
    """A part rendered with diffuse light alone over a noisy background: its normals at the
    true pose explain the grey level over its silhouette (R^2 near 1); the same part turned
    half about the viewing axis or moved by half its size does not; a pose behind the camera
    explains nothing."""
    mesh = tessellate(load_step(builtin_step("sharp_bracket")))
    camera = Camera(600.0, 600.0, 160.0, 120.0, 320, 240)
    centre_model = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
    centre = np.array([0.0, 0.0, 0.35])  # the part's centre in the camera frame

    def pose_at(R):
        return R, centre - R @ centre_model

    R, t = pose_at(rotation_about(np.array([1.0, 0.6, 0.2]), 0.9))
    background = np.random.default_rng(1).uniform(0, 255, (240, 320))
    light = Lighting(directions=((-0.4, -0.5, -1.0),), intensities=(0.8,), ambient=0.1)
    image = render(camera, [Placed(mesh, R, t, Material(specular=0.0))], background, lighting=light).image
    assert shading_fit(image, mesh, R, t, camera) > 0.95
    assert shading_fit(image, mesh, *pose_at(rot_z(np.pi) @ R), camera) < 0.8
    size = np.ptp(mesh.vertices, axis=0).max()
    assert shading_fit(image, mesh, R, t + np.array([size / 2, 0.0, 0.0]), camera) < 0.8
    assert shading_fit(image, mesh, R, -t, camera) == 0.0
    # a flat occluder over a fifth of the silhouette: left out by the fit, not held against the pose
    ys, xs = np.nonzero(render(camera, [Placed(mesh, R, t)]).mask)
    hidden = image.copy()
    hidden[ys.min():ys.min() + (ys.max() - ys.min()) // 5, :] = 128
    assert shading_fit(hidden, mesh, R, t, camera) > 0.9


def test_a_face_seen_square_on_has_one_normal_and_explains_nothing_but_its_mean():
    """A flat plate facing the camera gives every pixel of its silhouette the same normal, so
    the harmonics span only a constant (the normal equations are singular): the fit is the
    least-norm one, the mean, and explains none of a noisy image's spread, without failing."""
    half = 0.02
    vertices = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    plate = Mesh(vertices, np.array([[0, 2, 1], [0, 3, 2]], np.int32), np.tile([0.0, 0.0, -1.0], (4, 1)))
    camera = Camera(600.0, 600.0, 160.0, 120.0, 320, 240)
    image = np.random.default_rng(2).uniform(0, 255, (240, 320)).astype(np.float32)
    R, t = np.eye(3), np.array([0.0, 0.0, 0.3])
    assert len(rasterize(camera, [Posed(plate, R, t)]).pixels) > 10 * MIN_PIXELS  # seen, so fitted
    fit = shading_fit(image, plate, R, t, camera)
    assert np.isfinite(fit) and abs(fit) < 0.05
