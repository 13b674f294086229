"""Success and time of two versions of the estimator on the same bench scenes, in one process.

    python bench/versions_ab.py --base COMMIT [--n 6] [--parts sharp_bracket ...]
                                [--conditions clean ...] [--label NAME]

Times are only comparable within one run on a shared machine, and bench/accuracy.py runs one
version at a time; here the package of ``COMMIT`` (extracted with ``git archive`` and
imported under another name, its imports being relative) and this worktree's run image by
image, their order turning every image, each ``Estimator.estimate`` timed from the image to
the answer (edges included) at default parameters. Success is CONVENTIONS.md's (rotation
< 5 degrees, translation < 5 % of the diameter, and found), also up to the part's exact
symmetries; a found pose that is wrong even up to them is a wrong detection (precision at
``pose.min_score``). Scenes are bench/accuracy.py's
(varied look, seed 100, cached in data/bench); per-image records go to
data/bench/results/versions_ab_LABEL.json.
"""
from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import PARTS, add_scene_arguments, part_set, scene_path, step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402

BASE_PACKAGE = "brepose_ros_base"


def import_commit(commit: str, into: Path) -> str:
    """Extract brepose_ros of ``commit`` as package ``BASE_PACKAGE`` under ``into``."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", commit, "brepose_ros"], capture_output=True,
                             check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    (into / "brepose_ros").rename(into / BASE_PACKAGE)
    sys.path.insert(0, str(into))
    return BASE_PACKAGE


def version(package: str):
    """(AspectGraph, Estimator, load_scene, default parameters) of one version of the package.
    The parameters name the version's own shipped calibration: the package finds it under
    the name ``brepose_ros``, which for the extracted base is this worktree's (whose features
    the base may not know)."""
    params = importlib.import_module(f"{package}.params").EstimatorParams()
    shipped = Path(importlib.import_module(package).__file__).parent / "confidence.yaml"
    return (importlib.import_module(f"{package}.aspect_graph").AspectGraph,
            importlib.import_module(f"{package}.online.estimator").Estimator,
            importlib.import_module(f"{package}.scene_folder").load_scene,
            params.with_flat({"pose.confidence_file": str(shipped)}))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", required=True, help="commit to compare this worktree with")
    add_scene_arguments(parser, n=6, parts=["sharp_bracket", "base_attachment"],
                        conditions=["clean", "clutter", "occl30+clutter"])
    parser.add_argument("--label", default="run")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    out = cache / "results" / f"versions_ab_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        versions = {"base": version(import_commit(args.base, Path(tmp))), "new": version("brepose_ros")}
        for name in args.parts:
            step = step_file(PARTS[name], cache)
            mesh = tessellate(load_step(step))
            model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
            estimators = {}
            for label, (graph_class, estimator_class, load_scene, params) in versions.items():
                graph = graph_class.load(cached_graph_path(step, cache, 5.0))
                estimators[label] = (graph, estimator_class(graph, params), load_scene)
            for condition in args.conditions:
                folder = scene_path(cache, name, condition)
                # each version reads the scene with its own scene_folder, once per condition
                scenes = {label: load_scene(folder) for label, (_, _, load_scene) in estimators.items()}
                for i in range(args.n):
                    row = {"set": part_set(name), "part": name, "condition": condition, "image": i}
                    for label in (["base", "new"] if i % 2 == 0 else ["new", "base"]):
                        graph, estimator, _ = estimators[label]
                        scene = scenes[label]
                        entry = scene.entries[i]
                        image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                        start = time.perf_counter()
                        estimate = estimator.estimate(image, scene.camera)
                        ms = 1000 * (time.perf_counter() - start)
                        errors = (pose_errors(estimate.R, estimate.t, entry.R, entry.t, model, graph)
                                  if estimate.found else None)
                        row[label] = {"ms": ms, "success": bool(errors and errors.success),
                                      "success_sym": bool(errors and errors.success_sym),
                                      "found": bool(estimate.found), "score": float(estimate.score)}
                    rows.append(row)
                    print(f"{name} {condition} {i}: " + "  ".join(
                        f"{label} {int(row[label]['success'])} {row[label]['score']:.3f} {row[label]['ms']:.0f} ms "
                        f"(sym {int(row[label]['success_sym'])})"
                        for label in ("base", "new")), flush=True)
                    out.write_text(json.dumps(rows))
            for _, estimator, _ in estimators.values():
                estimator.close()
    print_table(rows)
    return 0


def print_table(rows: list[dict]) -> None:
    print("\n| set | condition | images | success base -> new | up to symmetry | found, wrong up to symmetry "
          "| median ms base -> new |")
    print("|---|---|---|---|---|---|---|")
    for key in dict.fromkeys((r["set"], r["condition"]) for r in rows):
        group = [r for r in rows if (r["set"], r["condition"]) == key]
        success, sym = ([np.mean([r[v][k] for r in group]) for v in ("base", "new")]
                        for k in ("success", "success_sym"))
        wrong = [sum(r[v]["found"] and not r[v]["success_sym"] for r in group) for v in ("base", "new")]
        ms = [np.median([r[v]["ms"] for r in group]) for v in ("base", "new")]
        print(f"| {key[0]} | {key[1]} | {len(group)} | {success[0]:.2f} -> {success[1]:.2f} | "
              f"{sym[0]:.2f} -> {sym[1]:.2f} | {wrong[0]} -> {wrong[1]} | {ms[0]:.0f} -> {ms[1]:.0f} |")


if __name__ == "__main__":
    sys.exit(main())
