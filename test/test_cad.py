"""The STEP loader refuses every unusable file with a message naming the cause."""
from __future__ import annotations

import numpy as np
import pytest

from brepose_ros.offline.cad import CadError, load_step

pytestmark = pytest.mark.cad


def test_builtin_box_is_loaded_in_metres(builtin_step):
    part = load_step(builtin_step("box"))  # 60 x 40 x 25 mm, centred on the origin
    assert part.n_solids == 1 and part.n_faces == 6
    assert np.allclose(part.center, 0.0, atol=1e-9)
    assert part.diameter == pytest.approx(np.sqrt(0.06**2 + 0.04**2 + 0.025**2), rel=1e-6)


def _truncated(tmp_path, builtin_step):
    data = builtin_step("box").read_bytes()
    path = tmp_path / "truncated.step"
    path.write_bytes(data[: len(data) // 2])
    return path


def _surface_only(tmp_path, builtin_step):
    import cadquery as cq

    path = tmp_path / "surface.step"
    cq.exporters.export(cq.Workplane().add(cq.Face.makePlane(10, 10)), str(path), exportType="STEP")
    return path


def _text(tmp_path, builtin_step):
    path = tmp_path / "notes.step"
    path.write_text("these are not the droids you are looking for\n")
    return path


def _empty(tmp_path, builtin_step):
    path = tmp_path / "empty.step"
    path.touch()
    return path


@pytest.mark.parametrize("make, message", [
    (lambda tmp_path, builtin_step: tmp_path / "missing.step", "does not exist"),
    (_empty, "is empty"),
    (_text, "is not a STEP file"),
    (_truncated, "is truncated"),
    (_surface_only, "holds no solid"),
], ids=["missing", "empty", "not-step", "truncated", "no-solid"])
def test_unusable_step_files_are_refused(tmp_path, builtin_step, make, message):
    with pytest.raises(CadError, match=message):
        load_step(make(tmp_path, builtin_step))


def test_files_over_the_size_limit_are_refused_before_parsing(builtin_step):
    with pytest.raises(CadError, match="over the limit"):
        load_step(builtin_step("box"), max_bytes=1000)


def test_construction_edges_beside_the_solid_do_not_count(tmp_path):
    """A far-away wire in the file (NIST CTC-01 has 78) must not grow the part's size."""
    import cadquery as cq

    box = cq.Workplane("XY").box(40, 20, 10).val()
    wire = cq.Edge.makeLine(cq.Vector(0, 0, 0), cq.Vector(500, 0, 0))
    path = tmp_path / "with_wire.step"
    cq.exporters.export(cq.Workplane("XY").add(cq.Compound.makeCompound([box, wire])), str(path), exportType="STEP")
    part = load_step(path)
    assert part.diameter == pytest.approx(np.linalg.norm([0.040, 0.020, 0.010]), rel=1e-3)
    assert np.allclose(part.center, 0.0, atol=1e-6)
