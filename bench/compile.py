"""Aspect-graph compile time and file size against the number of views and the part's size.

    python bench/compile.py                       # built-ins + ../shared/data/step parts
    python bench/compile.py --views 500 --large-views 2500 --large Motor1 ftc_10 --exact
    python bench/compile.py --parts Motor1 --views 2500 --large          # one row
    python bench/compile.py --parts STS3215 --views 1505 --large         # STEP against mesh rows

Every part is compiled at ``--views`` views with the default hidden-line method; the parts
whose file name contains one of ``--large`` also at ``--large-views`` views and, with
``--exact``, with exact HLR at ``--views`` for comparison. (All parts at 2,500 views with
both methods would hold two cores for about half an hour.) Time is the whole
``compile_aspect_graph`` call: process start, STEP loading, meshing, every view; "CPU
ms/view" counts this process and its workers, so other users' load does not inflate it
(wall time on an idle machine is about CPU time / workers + 3 s of process start).
Aim (issue 2): 2,500 views of a ~100-face part in under 60 s on 2 cores, under 50 MB.

Mesh rows (method "mesh", faces = triangles): the parts named by ``--mesh-of`` are also
compiled from their own tessellation written as an STL file in mm (STS3215_03a's has 4,485
vertices), right after their STEP row, and ``--meshes`` files (mm; by default the LM-O ape
scan, 5,841 vertices) at ``--views``. Aim (issue 13): a 5,000-vertex mesh at 1,505 views
within the STEP compile time of a part of similar size.
"""
from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

import trimesh

from brepose_ros.synthetic import shapes
from brepose_ros.offline.cad import load_step, tessellate
from brepose_ros.offline.compiler import compile_aspect_graph
from brepose_ros.offline.hidden_lines import DEFAULT_METHOD
from brepose_ros.viewsphere import fibonacci_step

SHARED_STEPS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "step"
LMO_APE = SHARED_STEPS.parent / "real" / "lmo_test_000002" / "models" / "obj_000001.ply"


def parts(folder: Path) -> list[Path]:
    builtins = [shapes.export_step(name, folder / f"{name}.step") for name in shapes.BUILTIN]
    return builtins + sorted(SHARED_STEPS.glob("*.st*p"))


def cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the pool's workers)."""
    return sum(resource.getrusage(who).ru_utime + resource.getrusage(who).ru_stime
               for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))


def mesh_of(step: Path, folder: Path) -> Path:
    """The part's own tessellation as a binary STL in millimetres."""
    mesh = tessellate(load_step(step))
    path = folder / f"{step.stem}.stl"
    trimesh.Trimesh(mesh.vertices * 1000.0, mesh.triangles).export(str(path))
    return path


def run(step: Path, views: int, method: str, workers: int, folder: Path) -> dict:
    started, cpu = time.perf_counter(), cpu_seconds()
    units = "mm" if method == "mesh" else None
    graph = compile_aspect_graph(step, step_deg=fibonacci_step(views), workers=workers, progress=False,
                                 units=units, **({} if units else {"method": method}))
    seconds, cpu = time.perf_counter() - started, cpu_seconds() - cpu
    size = graph.save(folder / "bench.brepose.npz").stat().st_size
    return dict(part=step.stem[:34], faces=graph.n_faces, method=method, views=graph.n_views,
                segments=graph.n_segments, seconds=seconds, mb=size / 1e6,
                cpu_ms_per_view=1e3 * cpu / graph.n_views, load=os.getloadavg()[0])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--parts", nargs="*", help="only parts whose file name contains one of these")
    p.add_argument("--views", type=int, default=500)
    p.add_argument("--large-views", type=int, default=2500)
    p.add_argument("--large", nargs="*", default=["Motor1_holder", "nist_ftc_10"])
    p.add_argument("--exact", action="store_true", help="also exact HLR for the large parts")
    p.add_argument("--mesh-of", nargs="*", default=["STS3215"],
                   help="parts also compiled from their tessellation as an STL mesh")
    p.add_argument("--meshes", nargs="*", type=Path, default=[LMO_APE] if LMO_APE.exists() else [],
                   help="mesh files in mm, compiled at --views")
    p.add_argument("--workers", type=int, default=2)
    args = p.parse_args()
    header = (f"{'part':34} {'faces':>5} {'method':>6} {'views':>5} {'segments':>8} {'seg/view':>8} "
              f"{'time s':>7} {'MB':>6} {'CPU ms/view':>11} {'load':>5}")
    print(f"workers {args.workers}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}\n{header}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for step in parts(folder):
            if args.parts and not any(name in step.name for name in args.parts):
                continue
            large = any(name in step.name for name in args.large)
            runs = [(args.views, DEFAULT_METHOD)]
            if large:
                runs += [(args.large_views, DEFAULT_METHOD)] + ([(args.views, "exact")] if args.exact else [])
            runs = [(step, views, method) for views, method in runs]
            if any(name in step.name for name in args.mesh_of):
                runs.append((mesh_of(step, folder), args.views, "mesh"))
            for model, views, method in runs:
                print_row(run(model, views, method, args.workers, folder))
        for mesh in args.meshes:
            print_row(run(mesh, args.views, "mesh", args.workers, folder))


def print_row(r: dict) -> None:
    print(f"{r['part']:34} {r['faces']:5d} {r['method']:>6} {r['views']:5d} {r['segments']:8d} "
          f"{r['segments'] / r['views']:8.0f} {r['seconds']:7.1f} {r['mb']:6.1f} "
          f"{r['cpu_ms_per_view']:11.1f} {r['load']:5.1f}", flush=True)


if __name__ == "__main__":
    main()
