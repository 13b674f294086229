"""Props of the varied scene look: closed, outward-facing meshes of unit size; backgrounds
of every kind; camera blur and noise."""
from __future__ import annotations

import numpy as np
import pytest

from brepose_ros.synthetic.looks import BACKGROUNDS, background, camera_effects, random_look
from brepose_ros.synthetic.props import KINDS, box_mesh, stretched, unit_prop


def signed_volume(mesh) -> float:
    tri = mesh.vertices[mesh.triangles]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("kind", KINDS + ("part",))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_props_are_closed_outward_and_unit_sized(kind, seed):
    part = stretched(box_mesh(1.0, 1.0, 1.0), (0.03, 0.01, 0.02))
    mesh = unit_prop(kind, np.random.default_rng(seed), (part,))
    assert np.ptp(mesh.vertices, axis=0).max() == pytest.approx(1.0)
    assert np.allclose(np.linalg.norm(mesh.normals, axis=1), 1.0)
    # Outward counter-clockwise triangles enclose a positive volume (blocks overlap, so more).
    assert signed_volume(mesh) > 0.005
    if kind not in ("blocks",):
        _, same = np.unique(np.round(mesh.vertices, 9), axis=0, return_inverse=True)
        edges = np.sort(same.reshape(-1)[mesh.triangles[:, [0, 1, 1, 2, 2, 0]]].reshape(-1, 2), axis=1)
        _, counts = np.unique(edges[edges[:, 0] != edges[:, 1]], axis=0, return_counts=True)
        assert (counts % 2 == 0).all(), "an edge with one triangle only: the surface has a hole"


def test_stretched_normals_stay_perpendicular_to_the_faces():
    mesh = stretched(unit_prop("polygon", np.random.default_rng(3)), (2.0, 0.5, 3.0))
    tri = mesh.vertices[mesh.triangles]
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    assert np.abs(np.einsum("ij,ij->i", face, mesh.normals[mesh.triangles[:, 0]])).min() > 1 - 1e-9


@pytest.mark.parametrize("kind", [kind for kind in BACKGROUNDS if kind != "blotches"])
def test_backgrounds_are_images_of_the_camera_size(kind):
    images = [background(np.random.default_rng(7), 64, 48, kind, color, None) for color in (False, True)]
    assert images[0].shape == (48, 64) and images[1].shape == (48, 64, 3)
    assert images[0].dtype == np.uint8 and images[0].std() > 0.5
    assert np.array_equal(images[0], background(np.random.default_rng(7), 64, 48, kind, False, None))


def test_blotchy_background_is_the_plain_looks():
    bench = np.full((48, 64), 90, np.uint8)
    assert background(np.random.default_rng(7), 64, 48, "blotches", False, lambda rng: bench) is bench


def test_camera_effects_blur_and_add_noise():
    edge = np.zeros((40, 40))
    edge[:, 20:] = 200.0
    look = random_look(np.random.default_rng(0), blur=0.6, noise=2.0, color=False)
    assert 0.3 <= look.blur <= 2.0 and 1.0 <= look.noise <= 6.0
    smooth = camera_effects(np.random.default_rng(0), edge, blur=2.0, noise=0.0)
    assert 0 < smooth[20, 19] < 200 and smooth[20, 0] == pytest.approx(0.0, abs=1e-6)
    streaked = camera_effects(np.random.default_rng(0), edge, blur=0.0, noise=0.0, motion=7.0)
    assert 0 < streaked[20, 19] < 200  # horizontal motion smears the vertical edge
    noisy = camera_effects(np.random.default_rng(0), edge, blur=0.0, noise=3.0)
    assert np.std(noisy[:, :20]) == pytest.approx(3.0, rel=0.15)
