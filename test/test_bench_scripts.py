"""The bench scripts still import: each is a documented command (docs/results/) that reaches
into the estimator's modules by name, so a renamed function breaks it silently otherwise."""
import importlib
from pathlib import Path

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
