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
