"""Generated scenes: exact and reproducible ground truth, measured occlusion, strict loader."""
from __future__ import annotations

import dataclasses
import json
import shutil

import cv2
import numpy as np
import pytest

from brepose_ros.offline.cad import load_step, tessellate
from brepose_ros.cli import render as render_cli
from brepose_ros.synthetic.render import Placed, rasterize
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene, render_image
from brepose_ros.scene_folder import SceneError, load_scene

SMALL = dict(width=320, height=240, fx=300.0)


@pytest.fixture(scope="module")
def occluded(sample_step, tmp_path_factory):
    config = SceneConfig(**SMALL, occlusion=0.3, clutter=3, offcenter=True)
    return generate_scene(sample_step, tmp_path_factory.mktemp("scene") / "occluded", 4, seed=7, config=config)


def test_scene_folder_follows_the_conventions(occluded, sample_step):
    folder = occluded.folder
    assert (folder / "model.step").read_bytes() == sample_step.read_bytes()
    assert json.loads((folder / "camera.json").read_text())["width"] == 320
    records = json.loads((folder / "gt.json").read_text())
    assert [r["image"] for r in records] == [f"images/{i:06d}.png" for i in range(4)]
    assert all(len(r["R"]) == 9 and len(r["t"]) == 3 and r["clutter"] == 3 for r in records)
    assert cv2.imread(str(folder / records[0]["image"]), cv2.IMREAD_UNCHANGED).shape == (240, 320)
    loaded = load_scene(folder)
    assert loaded.camera == occluded.camera and loaded.step == folder / "model.step"
    for a, b in zip(loaded.entries, occluded.entries):
        assert a.image == b.image and a.path == b.path
        assert np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t)
        assert a.occlusion == b.occlusion and a.visible_fraction == b.visible_fraction


def test_occlusion_is_reached_and_measured_from_the_masks(occluded):
    part = load_step(occluded.step)
    mesh = tessellate(part)
    side = min(occluded.camera.width, occluded.camera.height)
    for entry in occluded.entries:
        assert entry.occlusion == pytest.approx(0.3, abs=0.03)
        assert entry.visible_fraction == pytest.approx(1.0 - entry.occlusion)
        full = rasterize(occluded.camera, [Placed(mesh, entry.R, entry.t)]).labels == 0
        visible = cv2.imread(str(occluded.folder / entry.image.replace("images", "masks")), 0) > 0
        assert not (visible & ~full).any()
        assert visible.sum() / full.sum() == pytest.approx(entry.visible_fraction)
        ys, xs = np.nonzero(full)  # the part lies in the central 80 % and spans 25-60 %
        assert xs.min() >= 0.1 * 320 - 1 and xs.max() <= 0.9 * 320 and ys.min() >= 0.1 * 240 - 1
        assert ys.max() <= 0.9 * 240
        assert 0.23 * side <= max(np.ptp(xs), np.ptp(ys)) + 1 <= 0.62 * side


def test_same_seed_same_scene(sample_step, tmp_path, occluded):
    config = SceneConfig(**SMALL, occlusion=0.3, clutter=3, offcenter=True)
    again = generate_scene(sample_step, tmp_path / "again", 2, seed=7, config=config)
    gt = json.loads((occluded.folder / "gt.json").read_text())
    assert json.loads((again.folder / "gt.json").read_text()) == gt[:2]
    for name in ("images/000000.png", "images/000001.png", "masks/000001.png"):
        assert (again.folder / name).read_bytes() == (occluded.folder / name).read_bytes()
    other = generate_scene(sample_step, tmp_path / "other", 1, seed=8, config=config)
    assert not np.array_equal(other.entries[0].R, occluded.entries[0].R)


def test_elevation_band_and_centred_part(sample_step, tmp_path):
    config = SceneConfig(**SMALL, elevation=(20.0, 40.0), noise=0.0, blur=0.0)
    scene = generate_scene(sample_step, tmp_path / "band", 3, seed=1, config=config)
    center = load_step(scene.step).center
    for entry in scene.entries:
        camera_in_model = -entry.R.T @ entry.t
        direction = (camera_in_model - center) / np.linalg.norm(camera_in_model - center)
        assert 20.0 - 1e-6 <= np.degrees(np.arcsin(direction[2])) <= 40.0 + 1e-6
        assert scene.camera.project(entry.R @ center + entry.t) == pytest.approx([159.5, 119.5])
        assert entry.occlusion == 0.0 and entry.visible_fraction == 1.0


def test_bad_requests_are_refused(sample_step, tmp_path):
    with pytest.raises(SceneError, match="occlusion"):
        SceneConfig(occlusion=0.7)
    with pytest.raises(SceneError, match="span"):
        SceneConfig(span=(0.5, 0.2))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(SceneError, match="not empty"):
        generate_scene(sample_step, tmp_path / "full", 1)


def test_loader_names_what_is_wrong(occluded, tmp_path):
    folder = tmp_path / "broken"
    shutil.copytree(occluded.folder, folder)
    records = json.loads((folder / "gt.json").read_text())

    def broken(record, match):
        (folder / "gt.json").write_text(json.dumps([record]))
        with pytest.raises(SceneError, match=match):
            load_scene(folder)

    broken({**records[0], "R": [1, 0, 0, 0, 1, 0, 0, 0, 2]}, "not a rotation")
    broken({**records[0], "t": [1, 2]}, "3 numbers")
    broken({**records[0], "image": "images/missing.png"}, "does not exist")
    (folder / "gt.json").write_text("{")
    with pytest.raises(SceneError, match="not valid JSON"):
        load_scene(folder)
    (folder / "model.step").unlink()
    with pytest.raises(SceneError, match="model.step"):
        load_scene(folder)
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nowhere")


def test_render_command(tmp_path, capsys):
    assert render_cli.main(["builtin:cube", str(tmp_path / "cubes"), "--n", "2", "--width", "160",
                            "--height", "120", "--fx", "150", "--occlusion", "0.2", "-q"]) == 0
    assert len(load_scene(tmp_path / "cubes").entries) == 2
    assert render_cli.main(["builtin:shaft", str(tmp_path / "shafts"), "--n", "1", "--width", "160",
                            "--height", "120", "--fx", "150", "--look", "varied", "-q"]) == 0
    assert "look" in json.loads((tmp_path / "shafts" / "gt.json").read_text())[0]
    assert render_cli.main(["builtin:nothing", str(tmp_path / "x"), "-q"]) == 2
    assert "unknown built-in part" in capsys.readouterr().err
    assert render_cli.main([str(tmp_path / "missing.step"), str(tmp_path / "y"), "-q"]) == 2
    assert "does not exist" in capsys.readouterr().err


VARIED = dict(**SMALL, look="varied", span=(0.15, 0.70), offcenter=True, clutter=3)


@pytest.fixture(scope="module")
def varied(sample_step, tmp_path_factory):
    """Six varied-look images at 40 % occlusion, with the cube as another part to use."""
    from brepose_ros.synthetic.props import box_mesh

    config = SceneConfig(**VARIED, occlusion=0.4)
    return generate_scene(sample_step, tmp_path_factory.mktemp("varied") / "scene", 6, seed=4,
                          config=config, distractors=[box_mesh(0.04, 0.04, 0.04)])


def test_varied_look_reaches_the_occlusion_with_any_occluder(varied):
    records = json.loads((varied.folder / "gt.json").read_text())
    for entry, record in zip(varied.entries, records):
        assert entry.occlusion == pytest.approx(0.4, abs=0.03)
        mask = cv2.imread(str(varied.folder / entry.image.replace("images", "masks")), 0) > 0
        assert mask.sum() > 0
    looks = [r["look"] for r in records]
    assert len({look["occluder"] for look in looks}) >= 3  # not only bars and pipes
    assert len({look["background"] for look in looks}) >= 2
    assert len({look["key_light_deg"] for look in looks}) == 6


def test_varied_look_is_the_same_for_the_same_seed(varied, sample_step, tmp_path):
    from brepose_ros.synthetic.props import box_mesh

    again = generate_scene(sample_step, tmp_path / "again", 2, seed=4, config=SceneConfig(**VARIED, occlusion=0.4),
                           distractors=[box_mesh(0.04, 0.04, 0.04)])
    assert json.loads((again.folder / "gt.json").read_text()) == json.loads((varied.folder / "gt.json").read_text())[:2]
    for name in ("images/000000.png", "images/000001.png", "masks/000001.png"):
        assert (again.folder / name).read_bytes() == (varied.folder / name).read_bytes()


def test_an_image_is_rendered_again_with_one_look_factor_changed(varied, sample_step):
    """render_image redraws a scene's image to the byte; with its look changed the pose and
    the rest of the look stay: without blur and noise, a horizontal motion blur of 9 px is
    the sharp image under a 9 px horizontal box, everything else the same."""
    from brepose_ros.synthetic.props import box_mesh

    part = load_step(sample_step)
    mesh, config, distractors = tessellate(part), SceneConfig(**VARIED, occlusion=0.4), [box_mesh(0.04, 0.04, 0.04)]
    image, _, R, t, _, record = render_image(mesh, part.center, config, 4, 1, distractors)
    assert image.tobytes() == cv2.imread(str(varied.entries[1].path), cv2.IMREAD_UNCHANGED).tobytes()

    def rendered(motion, angle):
        return render_image(mesh, part.center, config, 4, 1, distractors, lambda look: dataclasses.replace(
            look, blur=0.0, noise=0.0, motion=motion, motion_angle=angle))

    sharp, (smeared, _, R2, t2, _, record2) = rendered(0.0, 0.0)[0].astype(float), rendered(9.0, 0.0)
    assert np.array_equal(R, R2) and np.array_equal(t, t2)
    assert record2 == record | {"blur": 0.0, "noise": 0.0, "motion": 9.0}
    along, across = (cv2.blur(sharp, size, borderType=cv2.BORDER_REFLECT) for size in ((9, 1), (1, 9)))
    assert np.abs(smeared - along).mean() < 0.5 < 2.0 < np.abs(smeared - across).mean()


def test_look_changes_the_image_not_the_pose(sample_step, tmp_path):
    plain = generate_scene(sample_step, tmp_path / "plain", 1, seed=5, config=SceneConfig(**SMALL))
    varied = generate_scene(sample_step, tmp_path / "varied", 1, seed=5, config=SceneConfig(**SMALL, look="varied"))
    assert np.array_equal(plain.entries[0].R, varied.entries[0].R)
    assert np.array_equal(plain.entries[0].t, varied.entries[0].t)
    assert "look" not in json.loads((plain.folder / "gt.json").read_text())[0]
    images = [cv2.imread(str(s.entries[0].path), 0).astype(float) for s in (plain, varied)]
    assert np.abs(images[0] - images[1]).mean() > 5
    with pytest.raises(SceneError, match="look"):
        SceneConfig(look="fancy")


def test_part_size_spans_the_requested_range(sample_step, tmp_path):
    config = SceneConfig(**SMALL, look="varied", span=(0.15, 0.70), noise=0.0, blur=0.0)
    scene = generate_scene(sample_step, tmp_path / "sizes", 12, seed=6, config=config)
    mesh = tessellate(load_step(scene.step))
    spans = []
    for entry in scene.entries:
        ys, xs = np.nonzero(rasterize(scene.camera, [Placed(mesh, entry.R, entry.t)]).labels == 0)
        spans.append((max(np.ptp(xs), np.ptp(ys)) + 1) / 240)
    assert 0.14 <= min(spans) and max(spans) <= 0.72
    assert min(spans) < 0.3 and max(spans) > 0.5  # the range is used, not one size
