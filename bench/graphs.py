"""Aspect graphs the benchmarks share, compiled once into a cache folder (data/bench/).

A cached file's name carries the graph format version, so that checkouts on different
format versions sharing one data/ folder each compile and keep their own file, the symmetry
detection's version (``offline.symmetry.DETECTION_VERSION``) and "-surface": a graph of the
same format found with an older detection, or cached before graphs held the part's surface,
is not compiled again (minutes) but copied with its symmetries found anew and the surface
added (seconds).
"""
from __future__ import annotations

from pathlib import Path

from brepose_ros.aspect_graph import FORMAT_VERSION, SUFFIX, AspectGraph
from brepose_ros.offline.cad import load_step
from brepose_ros.offline.compiler import compile_aspect_graph, surface_mesh, with_surface, with_symmetries
from brepose_ros.offline.symmetry import DETECTION_VERSION


def cached_graph_path(step: Path, cache: Path, step_deg: float, label: str | None = None,
                      lonlat: int | None = None) -> Path:
    """``cache/<stem>_<label>_v<FORMAT_VERSION>s<DETECTION_VERSION>-surface.brepose.npz``
    (label: ``<step_deg>deg``, or ``lonlat<K>`` on the paper's grid of density ``lonlat``), the
    aspect graph of ``step``, compiled there first if absent (module doc)."""
    label = label or (f"lonlat{lonlat}" if lonlat else f"{step_deg:g}deg")
    path = cache / f"{step.stem}_{label}_v{FORMAT_VERSION}s{DETECTION_VERSION}-surface{SUFFIX}"
    if not path.exists():
        older = sorted([*cache.glob(f"{step.stem}_{label}_v{FORMAT_VERSION}{SUFFIX}"),
                        *cache.glob(f"{step.stem}_{label}_v{FORMAT_VERSION}s*{SUFFIX}")])
        if older:
            surface = surface_mesh(load_step(step))
            with_surface(with_symmetries(AspectGraph.load(older[-1]), surface), surface).save(path)
        else:
            compile_aspect_graph(step, step_deg=step_deg, lonlat=lonlat).save(path)
    return path
