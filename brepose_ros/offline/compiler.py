"""Stage 2 (offline): compile the aspect graph of a part, view by view in parallel processes.

For each view on the sphere (``viewsphere``) the visible line sections are laid out flat
as the ``aspect_graph`` file format describes. A STEP file's lines come from OpenCascade's
hidden-line removal (``cad``, ``hidden_lines``), a mesh file's (PLY, STL, OBJ) from its
creases and outlines (``mesh``, ``mesh_lines``); both removers have the same interface.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from ..aspect_graph import AspectGraph, AspectGraphError
from ..geometry import look_at_rotation, unit_rows
from ..metric_space import normalisation_of
from ..viewsphere import fibonacci_directions, lonlat_directions, view_ups
from .cad import Mesh, load_step, tessellate, vertex_normals
from .hidden_lines import (DEFAULT_CHORD_TOLERANCE, DEFAULT_METHOD, DEFAULT_MIN_LENGTH, KIND_NAMES,
                           HiddenLineRemover, view_coordinates)
from .mesh import MeshPart, is_mesh_file, load_mesh
from .mesh_lines import DEFAULT_CREASE_ANGLE_DEG, MeshLineRemover
from .symmetry import NEAR_SHARE, TOLERANCE, detect_symmetries

#: Golden-spiral spacing of the views: about 1,500 views, no direction more than 4 degrees
#: from its nearest view.
DEFAULT_STEP_DEG = 5.0


_remover: HiddenLineRemover | MeshLineRemover | None = None  # one per worker process


def _load(model_path: str, units: str | None):
    """The part and the class of its hidden-line remover, by the file's kind."""
    if is_mesh_file(model_path):
        return load_mesh(model_path, units), MeshLineRemover
    if units is not None:
        raise ValueError(f"{Path(model_path).name}: units apply to mesh files only; "
                         f"a STEP file declares its own")
    return load_step(model_path), HiddenLineRemover


def _start_worker(model_path: str, units: str | None, options: dict) -> None:
    global _remover
    part, remover = _load(model_path, units)
    _remover = remover(part, **options)


def _visible_in_worker(task):
    return _visible(_remover, task)


def _visible(remover: HiddenLineRemover | MeshLineRemover,
             task: tuple[int, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """3D sections and kinds of a run of views (index of the first, their rotations)."""
    first, rotations = task
    results = []
    for i, rotation in enumerate(rotations, start=first):
        try:
            view = remover.segments(rotation)
        except Exception as error:  # OCCT exceptions do not pickle back to the parent
            raise AspectGraphError(f"hidden-line removal failed for view {i} "
                                   f"(direction {np.round(rotation[2], 4).tolist()}): {error}") from None
        results.append((view.segments_3d, view.kinds))
    return results


def _run(part, remover, model_path: str, units: str | None, tasks: list, options: dict, workers: int):
    """Results of the tasks in order, in this process or in a pool of ``workers``."""
    if workers == 1:
        remover = remover(part, **options)
        yield from (_visible(remover, task) for task in tasks)
        return
    import multiprocessing

    # spawn: a forked child deadlocks in OCCT's STEP reader. Each worker loads the file itself.
    with multiprocessing.get_context("spawn").Pool(workers, _start_worker, (model_path, units, options)) as pool:
        yield from pool.imap(_visible_in_worker, tasks)


def compile_aspect_graph(step_path: str | Path, step_deg: float = DEFAULT_STEP_DEG, lonlat: int | None = None,
                         workers: int | None = None, include_smooth: bool = False,
                         chord_tolerance: float = DEFAULT_CHORD_TOLERANCE, min_length: float = DEFAULT_MIN_LENGTH,
                         method: str = DEFAULT_METHOD, progress: bool = True, units: str | None = None,
                         crease_angle_deg: float = DEFAULT_CREASE_ANGLE_DEG) -> AspectGraph:
    """Compile the aspect graph of a part: a STEP file, or a PLY, STL or OBJ mesh whose
    length ``units`` (``mesh.UNITS``) must be given.

    Views: a golden-spiral sphere with neighbours ``step_deg`` apart, or with ``lonlat=K``
    the seed paper's longitude/latitude grid of density K. ``workers`` processes (default:
    one per CPU) each load the STEP file themselves, since OCCT shapes cannot be sent
    between processes. ``chord_tolerance`` and ``min_length`` are fractions of the model
    diameter (``hidden_lines``). ``method`` and ``include_smooth`` apply to STEP parts,
    ``crease_angle_deg`` to meshes (``mesh_lines``). Raises CadError (MeshError) for an
    unusable model file and AspectGraphError when a view cannot be computed.

    With several workers the processes are spawned, so a calling script needs the usual
    ``if __name__ == "__main__":`` guard (the console script and bench have it).
    """
    from tqdm import tqdm

    step_path = str(step_path)
    if is_mesh_file(step_path):
        if include_smooth:
            raise ValueError("smooth seams (--smooth) exist only in a STEP part's B-Rep, not in a mesh")
        options = dict(chord_tolerance=chord_tolerance, min_length=min_length, crease_angle_deg=crease_angle_deg)
        MeshLineRemover.check_options(**options)
        source = dict(source="mesh", source_units=units)
    else:
        options = dict(method=method, chord_tolerance=chord_tolerance, min_length=min_length,
                       include_smooth=include_smooth)
        HiddenLineRemover.check_options(method, chord_tolerance, min_length)
        source = dict(source="step")
    part, remover = _load(step_path, units)
    directions = lonlat_directions(lonlat) if lonlat is not None else fibonacci_directions(step_deg)
    ups = view_ups(directions)
    rotations = np.array([look_at_rotation(d, u) for d, u in zip(directions, ups)])
    workers = max(1, min(workers or os.cpu_count() or 1, len(rotations)))
    chunk = max(1, min(32, len(rotations) // (4 * workers)))
    tasks = [(i, rotations[i: i + chunk]) for i in range(0, len(rotations), chunk)]
    views = []
    with tqdm(total=len(rotations), unit="view", disable=not progress, desc=Path(step_path).name) as bar:
        for batch in _run(part, remover, step_path, units, tasks, options, workers):
            views.extend(batch)
            bar.update(len(batch))
    params = dict(units="m", projection="orthographic", up="geometry.default_up",
                  sampling="lonlat" if lonlat is not None else "fibonacci",
                  step_deg=None if lonlat is not None else float(step_deg), lonlat=lonlat,
                  kinds=list(KIND_NAMES), step_file=Path(step_path).name,
                  symmetry=dict(tolerance=TOLERANCE, near_share=NEAR_SHARE), **source, **options)
    return _assemble(part, params, directions, rotations, views)


def _assemble(part, params, directions, rotations, views) -> AspectGraph:
    """Every view's sections in its view coordinates, laid out flat, and the part's
    symmetries found on them."""
    seg_xy, xy_origin, xy_scale = [], [], []
    for i, ((seg_3d, _), rotation) in enumerate(zip(views, rotations)):
        xy = view_coordinates(seg_3d, rotation, part.center)
        if len(xy) == 0:
            raise AspectGraphError(f"view {i} (direction {np.round(directions[i], 4).tolist()}) shows no "
                                   f"edge longer than the minimum length; lower min_length")
        frame = normalisation_of(xy)  # the view's own origin and unit for float32 storage
        seg_xy.append(frame.apply(xy).astype(np.float32))
        xy_origin.append(frame.center)
        xy_scale.append(frame.scale)
    counts = [len(s) for s in seg_xy]
    seg_3d = np.concatenate([s for s, _ in views]).astype(np.float64)
    seg_kind = np.concatenate([k for _, k in views]).astype(np.uint8)
    surface = surface_mesh(part)
    return with_surface(with_symmetries(AspectGraph(
        step_sha256=part.sha256, params=params, model_center=np.asarray(part.center, dtype=np.float64),
        model_diameter=float(part.diameter), n_faces=int(part.n_faces),
        view_directions=np.asarray(directions, dtype=np.float64),
        view_rotations=np.asarray(rotations, dtype=np.float64),
        seg_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        seg_xy=np.concatenate(seg_xy), xy_origin=np.array(xy_origin, dtype=np.float64),
        xy_scale=np.array(xy_scale, dtype=np.float64),
        seg_3d=seg_3d, seg_kind=seg_kind,
        colour_histogram=part.colour_histogram if isinstance(part, MeshPart) else None), surface), surface)


def surface_mesh(part) -> Mesh:
    """The part's surface: a ``MeshPart``'s own triangles with smooth normals (a scan's), a
    loaded STEP part tessellated (normals split between its faces)."""
    if isinstance(part, MeshPart):
        return Mesh(part.vertices, part.triangles, vertex_normals(part.vertices, part.triangles))
    return tessellate(part)


def with_surface(graph: AspectGraph, surface: Mesh) -> AspectGraph:
    """The graph holding the part's surface (``surface_mesh``), as the file stores it (a normal
    of no length, which the load check would refuse, as +z)."""
    return dataclasses.replace(graph, surface_vertices=surface.vertices.astype(np.float32),
                               surface_normals=unit_rows(surface.normals, [0.0, 0.0, 1.0]).astype(np.float32),
                               surface_triangles=surface.triangles.astype(np.int32))


def with_symmetries(graph: AspectGraph, surface: Mesh) -> AspectGraph:
    """The graph with the symmetries found on its edge sections and the part's surface
    (``surface_mesh``); also re-detects them in a graph compiled before the detection changed
    (bench/graphs.py)."""
    found = detect_symmetries(graph.seg_3d, graph.seg_kind, graph.model_diameter,
                              (surface.vertices, surface.triangles))
    return dataclasses.replace(graph, symmetry_rotations=found.rotations, symmetry_translations=found.translations,
                               symmetry_shares=found.shares, symmetry_axes=found.axes,
                               symmetry_axis_shares=found.axis_shares)
