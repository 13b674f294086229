"""Built-in parts built with CadQuery, so tests, benchmarks and the demo need no files.

Dimensions are in millimetres, as in a STEP file; ``export_step`` writes them out and the
CAD loader converts to metres like any other part. ``sharp_bracket`` and ``rounded_bracket``
are the seed paper's two test objects (section 7.1), ``cube`` and ``cylinder`` its training
shapes (section 6), ``sample_bracket`` the bundled part of the README. ``shaft``, ``flange``
and ``notched_plate`` are the hard cases of issue 11: a rotational part with few straight
edges, a disc with a bolt circle, and a plate that is symmetric but for one small notch.
"""
from __future__ import annotations

from pathlib import Path

import cadquery as cq


def cube(size: float = 40.0) -> cq.Workplane:
    return cq.Workplane("XY").box(size, size, size)


def box(dx: float = 60.0, dy: float = 40.0, dz: float = 25.0) -> cq.Workplane:
    return cq.Workplane("XY").box(dx, dy, dz)


def cylinder(radius: float = 20.0, height: float = 50.0) -> cq.Workplane:
    return cq.Workplane("XY").cylinder(height, radius)


def l_block() -> cq.Workplane:
    """A 60 x 40 x 30 block with a 30 x 15 step cut along its length: a training shape with no
    rotational symmetry, so that its wrong views are not forgiven as a cube's are."""
    return cq.Workplane("XZ").polyline([(0, 0), (60, 0), (60, 15), (30, 15), (30, 30), (0, 30)]).close() \
        .extrude(-40).translate((-30, -20, -15))


def wedge() -> cq.Workplane:
    """A right wedge, legs 60 and 30, 40 deep: the other training shape without rotational symmetry."""
    return cq.Workplane("XZ").polyline([(0, 0), (60, 0), (0, 30)]).close().extrude(-40).translate((-20, -20, -10))


def sharp_bracket() -> cq.Workplane:
    """An L bracket with a rectangular window and two square holes: only straight edges."""
    base = cq.Workplane("XY").box(80, 50, 8).translate((0, 0, 4))
    wall = cq.Workplane("XY").box(8, 50, 50).translate((-36, 0, 25))
    part = base.union(wall)
    part = part.cut(cq.Workplane("XY").box(16, 12, 20).translate((15, 10, 4)))
    part = part.cut(cq.Workplane("XY").box(16, 12, 20).translate((15, -10, 4)))
    part = part.cut(cq.Workplane("YZ").rect(24, 18).extrude(40, both=True).translate((-36, 0, 30)))
    return part


def rounded_bracket() -> cq.Workplane:
    """The same L bracket with filleted edges and round holes: curves everywhere."""
    base = cq.Workplane("XY").box(80, 50, 8).translate((0, 0, 4))
    wall = cq.Workplane("XY").box(8, 50, 50).translate((-36, 0, 25))
    part = base.union(wall).edges("|Y").fillet(3.0)
    part = part.faces(">Z").workplane().pushPoints([(15, 10), (15, -10)]).hole(12)
    part = part.faces("<X").workplane(centerOption="CenterOfBoundBox").center(0, 5).hole(18)
    return part


def sample_bracket() -> cq.Workplane:
    """The bundled sample: a mounting bracket with a rib, two holes and filleted corners."""
    plate = cq.Workplane("XY").box(90, 60, 10).edges("|Z").fillet(8.0)
    plate = plate.faces(">Z").workplane().pushPoints([(-30, -18), (-30, 18)]).hole(10)
    block = cq.Workplane("XY").box(30, 60, 35).translate((30, 0, 22.5))
    block = block.faces(">Z").workplane().hole(14)
    part = plate.union(block)
    rib = cq.Workplane("XZ").polyline([(0, 5), (15, 5), (15, 30)]).close().extrude(5, both=True)
    return part.union(rib)


def shaft() -> cq.Workplane:
    """A round shaft with a flat at one end and a cross hole: curved, nearly rotational."""
    part = cq.Workplane("XY").cylinder(70, 10).edges().chamfer(1.0)
    flat = cq.Workplane("XY").box(20, 8, 24).translate((0, 10 + 4 - 3, 35 - 12))  # 3 mm deep
    part = part.cut(flat)
    return part.cut(cq.Workplane("XZ").cylinder(30, 3).translate((0, 0, -15)))


def flange() -> cq.Workplane:
    """A disc with a hub, a through bore and six bolt holes on a circle."""
    disc = cq.Workplane("XY").circle(45).extrude(10)
    hub = cq.Workplane("XY").workplane(offset=10).circle(22).extrude(18)
    part = disc.union(hub).faces(">Z").workplane().hole(24)
    return part.faces("<Z").workplane().polarArray(34, 0, 360, 6).hole(8)


def notched_plate() -> cq.Workplane:
    """A plate with four corner holes and a slot, symmetric but for one small edge notch."""
    part = cq.Workplane("XY").box(90, 60, 8).edges("|Z").fillet(4.0)
    part = part.faces(">Z").workplane().rect(70, 40, forConstruction=True).vertices().hole(7)
    part = part.faces(">Z").workplane().slot2D(30, 10).cutThruAll()
    return part.cut(cq.Workplane("XY").box(8, 6, 10).translate((20, 30, 0)))


BUILTIN = {
    "cube": cube,
    "box": box,
    "cylinder": cylinder,
    "l_block": l_block,
    "wedge": wedge,
    "sharp_bracket": sharp_bracket,
    "rounded_bracket": rounded_bracket,
    "sample_bracket": sample_bracket,
    "shaft": shaft,
    "flange": flange,
    "notched_plate": notched_plate,
}


def export_step(part: cq.Workplane | str, path: str | Path) -> Path:
    """Write a built-in part (by name or as a Workplane) to a STEP file in millimetres."""
    if isinstance(part, str):
        if part not in BUILTIN:
            raise KeyError(f"unknown built-in part {part!r}; choose from {', '.join(BUILTIN)}")
        part = BUILTIN[part]()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cq.exporters.export(part, str(path), exportType="STEP")
    return path
