"""Stage 0: read a STEP (B-Rep) file into an OpenCascade shape in metres.

CadQuery/OCCT hands lengths back in millimetres whatever unit the file declares, so the
shape is scaled by 1e-3 once, here; everything downstream works in metres
(../shared/CONVENTIONS.md). The model frame is the file's own: nothing is re-centred.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..aspect_graph import file_sha256
from ..geometry import unit_rows

#: Refuse files larger than this before parsing (a STEP part of a few hundred faces is
#: well under 10 MB; a whole assembly or a wrong file is what larger ones usually are).
MAX_STEP_BYTES = 64 * 1024 * 1024

MM_TO_M = 1e-3


class CadError(ValueError):
    """A STEP file that cannot be used, with the reason in the message."""


@dataclass
class Part:
    """A solid part: the OCCT shape in metres plus what every later stage needs to know."""

    shape: object  # OCP compound of the solids, metres, model frame of the STEP file
    sha256: str  # of the STEP file's bytes: ties compiled data to its source
    source: str
    center: np.ndarray  # bounding-box centre, metres, model frame
    diameter: float  # bounding-box diagonal, metres (an upper bound of the true diameter)
    n_faces: int
    n_solids: int


def _read_step_shape(path: Path):
    """Parse with OCCT's STEP reader and return the whole transferred shape."""
    from OCP.IFSelect import IFSelect_ReturnStatus
    from OCP.STEPControl import STEPControl_Reader

    reader = STEPControl_Reader()
    status = reader.ReadFile(str(path))
    if status != IFSelect_ReturnStatus.IFSelect_RetDone:
        raise CadError(f"{path} is not a readable STEP file (OCCT reader status {status.name})")
    if reader.TransferRoots() == 0:
        raise CadError(f"{path} is a STEP file but holds no transferable geometry")
    return reader.OneShape()


def load_step(path: str | Path, max_bytes: int = MAX_STEP_BYTES) -> Part:
    """Load a STEP file (a solid, a compound or an assembly of solids) in metres.

    Raises CadError naming the cause for a missing, oversized, non-STEP, truncated or
    solid-less file.
    """
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
    from OCP.gp import gp_Trsf
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer

    path = Path(path)
    size = checked_size(path, "STEP file", max_bytes, CadError)
    with open(path, "rb") as stream:
        head = stream.read(64)
    if not head.lstrip().startswith(b"ISO-10303-21"):
        raise CadError(f"{path} is not a STEP file (it does not start with ISO-10303-21)")
    with open(path, "rb") as stream:
        stream.seek(max(0, size - 256))
        tail = stream.read()
    if b"END-ISO-10303-21" not in tail:
        raise CadError(f"STEP file {path} is truncated (no END-ISO-10303-21 at its end)")

    shape_mm = _read_step_shape(path)

    def count(shape, kind):
        explorer, n = TopExp_Explorer(shape, kind), 0
        while explorer.More():
            n += 1
            explorer.Next()
        return n

    n_solids = count(shape_mm, TopAbs_SOLID)
    if n_solids == 0:
        raise CadError(f"STEP file {path} holds no solid (only surfaces, curves or nothing)")

    scale = gp_Trsf()
    scale.SetScaleFactor(MM_TO_M)
    shape = solids_of(BRepBuilderAPI_Transform(shape_mm, scale, True).Shape())
    lo, hi = bounding_box(shape)
    return Part(shape=shape, sha256=file_sha256(path), source=str(path),
                center=(lo + hi) / 2.0, diameter=float(np.linalg.norm(hi - lo)),
                n_faces=count(shape, TopAbs_FACE), n_solids=n_solids)


def checked_size(path: Path, kind: str, max_bytes: int, error: type[CadError]) -> int:
    """The size of a model file, or ``error`` naming why it cannot be read: missing, empty
    or over ``max_bytes`` (checked before any parsing, which could take all memory)."""
    if not path.is_file():
        raise error(f"{kind} {path} does not exist")
    size = path.stat().st_size
    if size == 0:
        raise error(f"{kind} {path} is empty")
    if size > max_bytes:
        raise error(f"{kind} {path} is {size / 1e6:.1f} MB, over the limit of {max_bytes / 1e6:.0f} MB")
    return size


def solids_of(shape):
    """A compound of the shape's solids only: a camera sees no construction wires or lone
    surfaces, which some STEP files carry beside the part (NIST CTC-01 has 78 such edges,
    which made its bounding box 1.35 m instead of 0.93 m)."""
    from OCP.BRep import BRep_Builder
    from OCP.TopAbs import TopAbs_SOLID
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS_Compound

    builder, compound = BRep_Builder(), TopoDS_Compound()
    builder.MakeCompound(compound)
    explorer = TopExp_Explorer(shape, TopAbs_SOLID)
    while explorer.More():
        builder.Add(compound, explorer.Current())
        explorer.Next()
    return compound


def bounding_box(shape) -> tuple[np.ndarray, np.ndarray]:
    """Tight axis-aligned bounding box (min corner, max corner)."""
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    box = Bnd_Box()
    BRepBndLib.AddOptimal_s(shape, box, False, False)
    x0, y0, z0, x1, y1, z1 = box.Get()
    return np.array([x0, y0, z0]), np.array([x1, y1, z1])


@dataclass
class Mesh:
    """A triangle mesh of a part's surface, metres, model frame."""

    vertices: np.ndarray  # (N, 3) float64
    triangles: np.ndarray  # (M, 3) int32, outward counter-clockwise
    normals: np.ndarray  # (N, 3) per-vertex normals: smooth within a face, split between faces


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Smooth normals: the area-weighted mean of each vertex's triangles' normals (+z for a
    vertex of degenerate triangles only, which has none)."""
    tri = vertices[triangles]
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices, dtype=np.float64)
    for corner in range(3):
        np.add.at(normals, triangles[:, corner], face)
    return unit_rows(normals, [0.0, 0.0, 1.0])


def tessellate(part: Part, relative_deflection: float = 2e-3, angular_deflection: float = 0.3) -> Mesh:
    """Triangulate every face; the chord deflection is relative to the part's diameter.

    Vertices are not shared between faces, so normals stay sharp across B-Rep edges and
    smooth inside a curved face: that is what makes the edges between faces visible in
    a shaded rendering.
    """
    from OCP.BRep import BRep_Tool
    from OCP.BRepLib import BRepLib_ToolTriangulatedShape
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.TopAbs import TopAbs_FACE, TopAbs_REVERSED
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopLoc import TopLoc_Location
    from OCP.TopoDS import TopoDS

    BRepMesh_IncrementalMesh(part.shape, relative_deflection * part.diameter, False, angular_deflection, True)
    vertices, triangles, normals = [], [], []
    offset = 0
    explorer = TopExp_Explorer(part.shape, TopAbs_FACE)
    while explorer.More():
        face = TopoDS.Face_s(explorer.Current())
        explorer.Next()
        location = TopLoc_Location()
        tri = BRep_Tool.Triangulation_s(face, location)
        if tri is None:
            continue
        trsf = location.Transformation()
        n = tri.NbNodes()
        pts = np.array([[c for c in tri.Node(i).Transformed(trsf).Coord()] for i in range(1, n + 1)])
        if not tri.HasNormals():
            BRepLib_ToolTriangulatedShape.ComputeNormals_s(face, tri)
        nrm = np.array([tri.Normal(i).Coord() for i in range(1, n + 1)], dtype=float)
        rot = np.array([[trsf.Value(r, c) for c in (1, 2, 3)] for r in (1, 2, 3)])
        nrm = nrm @ rot.T
        idx = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)], dtype=np.int64) - 1
        if face.Orientation() == TopAbs_REVERSED:
            idx = idx[:, ::-1]
            nrm = -nrm
        vertices.append(pts)
        normals.append(nrm)
        triangles.append(idx + offset)
        offset += n
    if not triangles:
        raise CadError(f"{part.source}: tessellation produced no triangles")
    nrm = np.concatenate(normals)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return Mesh(np.concatenate(vertices), np.concatenate(triangles).astype(np.int32), nrm)
