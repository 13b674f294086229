"""Built-in parts built with CadQuery, so tests, benchmarks and the demo need no files.

Dimensions are in millimetres, as in a STEP file; ``export_step`` writes them out and the
CAD loader converts to metres like any other part. ``sharp_bracket`` and ``rounded_bracket``
are the seed paper's two test objects (section 7.1), ``cube`` and ``cylinder`` its training
shapes (section 6), ``sample_bracket`` the bundled part of the README.
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


BUILTIN = {
    "cube": cube,
    "box": box,
    "cylinder": cylinder,
    "sharp_bracket": sharp_bracket,
    "rounded_bracket": rounded_bracket,
    "sample_bracket": sample_bracket,
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
