"""Shared fixtures: the bundled sample part and the real data beside the clone.

A test that asks for a STEP file (``builtin_step``, ``sample_step``, ``shared_data``) needs
the CAD stack and is marked ``cad`` here, so ``pytest -m "not cad and not ros"`` runs the
maths alone, without importing cadquery.
"""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (real STEP parts and LM-O photos); tests that need it skip without it."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not beside this clone")
    return SHARED_DATA


@pytest.fixture(scope="session")
def builtin_step(tmp_path_factory):
    """Factory: the STEP file of a built-in part, exported once per session."""
    folder = tmp_path_factory.mktemp("builtin_steps")
    cache: dict[str, Path] = {}

    def make(name: str) -> Path:
        from brepose_ros.synthetic import shapes  # cadquery: only for the tests that ask

        if name not in cache:
            cache[name] = shapes.export_step(name, folder / f"{name}.step")
        return cache[name]

    return make


@pytest.fixture(scope="session")
def sample_step(builtin_step) -> Path:
    return builtin_step("sample_bracket")


CAD_FIXTURES = {"builtin_step", "sample_step", "shared_data"}


def pytest_collection_modifyitems(items):
    for item in items:
        if CAD_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.cad)
