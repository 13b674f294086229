"""The bench scripts still import: each is a documented command (docs/results/) that reaches
into the estimator's modules by name, so a renamed function breaks it silently otherwise."""
import importlib
from pathlib import Path

import cv2
import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.parametrize("script", sorted(p.stem for p in BENCH.glob("*.py")))
def test_the_bench_script_imports(script):
    module = importlib.import_module(f"bench.{script}")
    assert callable(getattr(module, "main", None)) or script == "graphs"


def test_a_grown_bench_scene_keeps_its_first_images_and_leaves_no_side_folders(tmp_path, sample_step):
    from bench.accuracy import scene

    first = scene(tmp_path, "part", sample_step, "clean", 1, distractors=[])
    before = first.entries[0].path.read_bytes()
    grown = scene(tmp_path, "part", sample_step, "clean", range(1, 3), distractors=[])
    assert [e.path.name for e in grown.entries] == ["000001.png", "000002.png"]
    again = scene(tmp_path, "part", sample_step, "clean", 3, distractors=[])
    assert again.entries[0].path.read_bytes() == before
    assert sorted(p.name for p in again.folder.parent.iterdir()) == [again.folder.name, again.folder.name + ".lock"]


def test_the_look_split_bins_sizes_in_order_and_pools_by_condition():
    from bench.by_look import size_level, split

    levels = [size_level(s) for s in (0.05, 0.15, 0.3, 0.9)]
    assert levels == sorted(levels) == ["0.00-0.15", "0.15-0.25", "0.25-0.40", "0.40+"]
    look = {"background": "grid", "motion": 0.0, "key_light": 0.9}
    records = [{"condition": c, "right": r, "look": look, "size": 0.3} for c, r in
               (("clean", True), ("clean", False), ("clutter", True))]
    table = split(records)
    assert table["background"]["grid"]["clean"] == [True, False]
    assert table["motion blur"]["none"]["clutter"] == [True]


def test_compare_runs_counts_righted_and_lost_images_and_tests_their_split(tmp_path, capsys):
    import json

    from bench.compare_runs import main

    def run(path, rights):
        images = [{"image": f"{i:06d}.png", "found": True, "success": r, "success_sym": r}
                  for i, r in enumerate(rights)]
        path.write_text(json.dumps({"rows": [{"part": "shaft", "condition": "clean", "images": images}]}))
        return path

    before = run(tmp_path / "before.json", [True] * 2 + [False] * 10)
    after = run(tmp_path / "after.json", [False] * 2 + [True] * 10)
    assert main(["--before", str(before), "--after", str(after)]) == 0
    out = capsys.readouterr().out
    assert "| all | | 12 | 2 -> 10 |" in out
    assert "sign test: 10 righted, 2 lost, two-sided p = 0.039" in out


def test_the_occlusion_plot_pools_a_part_set_and_counts_the_metric_asked():
    from bench.plot_accuracy import curve

    def row(part, part_set, condition, occlusion, clutter, flags):
        return {"part": part, "set": part_set, "condition": condition, "occlusion": occlusion, "clutter": clutter,
                "images": [{"success": strict, "success_sym": up_to_symmetry} for strict, up_to_symmetry in flags]}

    rows = [row("a", "leave-out", "clean", 0.0, 0, [(True, True), (False, True)]),
            row("a", "leave-out", "clutter", 0.0, 4, [(False, False), (False, True)]),
            row("b", "leave-out", "occl30+clutter", 0.3, 4, [(False, True), (False, False)]),
            row("c", "tune", "clean", 0.0, 0, [(True, True)])]
    assert curve(rows, "leave-out", "success") == ([0.0, 30.0], [0.0, 0.0], 0.5)
    assert curve(rows, "leave-out", "success_sym") == ([0.0, 30.0], [0.5, 0.5], 1.0)


def test_the_occlusion_plot_is_drawn_from_runs_split_by_part(tmp_path):
    import json

    from bench.plot_accuracy import main

    def run(name, part_set):
        images = [{"success": True, "success_sym": True}, {"success": False}]
        rows = [{"part": name, "set": part_set, "condition": c, "occlusion": o, "clutter": k, "images": images}
                for c, o, k in (("clean", 0.0, 0), ("clutter", 0.0, 4), ("occl30+clutter", 0.3, 4))]
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"label": name, "look": "varied", "commit": "abc1234", "rows": rows}))
        return path

    figure = tmp_path / "figure.png"
    assert main([f"both={run('a', 'tune')}", f"both={run('b', 'leave-out')}", "--out", str(figure)]) == 0
    assert figure.stat().st_size > 1000


def test_an_operating_point_counts_right_and_wrong_found_poses_and_times_every_image():
    from bench.speed_accuracy import operating_point

    def image(found, right, ms):
        return {"found": found, "success_sym": right, "ms": ms}

    rows = [{"condition": "clean", "images": [image(True, True, 100), image(True, False, 200)]},
            {"condition": "clutter", "images": [image(False, True, 300), image(True, True, 400)]}]
    point = operating_point(rows)
    assert point["right"] == 2 and point["wrong"] == 1  # a right pose not found is not right
    assert point["by_condition"] == {"clean": 1, "clutter": 1}
    assert point["per_condition"] == {"clean": 2, "clutter": 2}
    assert point["median_ms"] == 250 and 300 < point["p90_ms"] < 400

def test_the_silhouette_contrast_tells_the_part_from_a_copy_inside_it_and_from_background():
    from bench.silhouette_contrast import band_contrast, quantised

    image = np.full((100, 100), 200, np.uint8)
    image[30:70, 30:70] = 60
    part, copy, patch = (np.zeros((100, 100), np.uint8) for _ in range(3))
    part[30:70, 30:70] = 1
    copy[40:60, 40:60] = 1  # a shrunken pose lying on the part: part on both sides of its outline
    patch[5:25, 5:25] = 1
    for shown in (image, cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)):
        bins, n_bins = quantised(shown)
        assert band_contrast(bins, n_bins, part, 4.0) == pytest.approx(1.0)
        assert band_contrast(bins, n_bins, copy, 4.0) == pytest.approx(0.0)
        assert band_contrast(bins, n_bins, patch, 4.0) == pytest.approx(0.0)
        assert 0.0 < band_contrast(bins, n_bins, np.roll(part, 20, axis=1), 4.0) < 0.5
    assert np.isnan(band_contrast(bins, n_bins, None, 4.0))

