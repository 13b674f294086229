"""The built-in parts of issue 11 are valid single solids with the features they promise."""
from __future__ import annotations

import numpy as np
import pytest

from brepose_ros.offline.cad import load_step

pytestmark = pytest.mark.cad


@pytest.mark.parametrize("name, faces", [("shaft", 8), ("flange", 12), ("notched_plate", 22), ("l_block", 8),
                                         ("wedge", 5)])
def test_new_parts_are_valid_solids(builtin_step, name, faces):
    from brepose_ros.synthetic import shapes

    assert shapes.BUILTIN[name]().val().isValid()
    part = load_step(builtin_step(name))
    assert part.n_solids == 1 and part.n_faces == faces


def test_shaft_is_round_flange_has_a_bolt_circle_and_the_plate_one_notch():
    import cadquery as cq

    from brepose_ros.synthetic import shapes

    shaft = shapes.shaft()
    assert len(shaft.faces("%CYLINDER").vals()) == 2  # the outside and the cross hole
    assert len(shaft.faces("%PLANE").vals()) == 4  # two ends, the flat and its shoulder
    assert len(shaft.faces("%CONE").vals()) == 2  # the chamfers
    flange = shapes.flange()
    holes = [f for f in flange.faces("%CYLINDER").vals() if f.Area() < 400]
    radii = [np.hypot(*f.Center().toTuple()[:2]) for f in holes]
    assert len(holes) == 6 and np.allclose(radii, 34.0, atol=1e-6)
    plate = shapes.notched_plate().val()
    mirrored = plate.mirror("YZ")
    # Symmetric but for the notch: the mirror image differs by the notch's volume only.
    assert plate.cut(mirrored).Volume() == pytest.approx(8 * 6 * 8 / 2, rel=0.05)
    assert isinstance(mirrored, cq.Shape)
