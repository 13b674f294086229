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
