"""Edge-stage variants at LM-O's true poses: how much of each part's visible model edge the
image's Canny pixels confirm, without running the estimator.

    python bench/real_lmo_edges.py [--frames 8] [--render] [--params FILE.yaml] \\
        [--variant NAME KEY=VALUE ...] [--results data/bench/real_lmo/results_estimator.json]

The targets, graphs, images and renders are bench/real_lmo.py's. Each variant is the edge
stage with some ``edges.*`` parameters changed (``--variant grey colour=false``; ``given``,
the parameters as given, always runs first; ``edges.colour`` is on by default). Per object and variant, medians over its
targets of:

* ``support``: the share of the true pose's projected visible model edges within
  ``pose.inlier_pixels`` of an edge pixel of like direction (real_lmo.py's column), raw;
* ``confirmed``: the same beyond what chance confirms there (``Shares.confirmed``: the
  local density of like edges is the chance, so a variant that only adds edge pixels
  everywhere does not gain);
* ``truth``: the estimator's score of the true pose (``scoring.pose_scores``);
* ``edges``: the share of the image's pixels that are edge pixels (per image, over all).

With ``--results`` (a results*.json of bench/real_lmo.py on the same frames) each target's
estimate from that run is scored on every variant's edges too: ``fooled`` counts the wrong
estimates that score at least as high as the truth. A variant whose edges make the truth
outscore the estimator's wrong poses more often gives the search and the score a chance; the
run's own estimates were chosen on the given parameters' edges, so this leans to ``given``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.real_lmo import (LMO, NAMES, RENDER_BACKGROUND, graph_of, load_targets, scene_meshes,  # noqa: E402
                            support)
from brepose_ros.camera import Camera  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import detect_edges  # noqa: E402
from brepose_ros.online.scoring import pose_scores  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.synthetic.render import Placed, render  # noqa: E402


def variant(text: list[str]) -> tuple[str, dict]:
    """``NAME KEY=VALUE ...`` -> (name, flat ``edges.*`` overrides), values parsed as YAML
    (checked by ``EstimatorParams.with_flat`` when applied)."""
    name, *pairs = text
    return name, {f"edges.{key}": yaml.safe_load(value) for key, value in (pair.split("=", 1) for pair in pairs)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=8, help="the first N frames")
    parser.add_argument("--step-deg", type=float, default=5.0, help="aspect graph view spacing")
    parser.add_argument("--params", type=Path, help="estimator parameter YAML (config/estimator.yaml layout)")
    parser.add_argument("--render", action="store_true", help="renderings of the true poses instead of the photos")
    parser.add_argument("--variant", nargs="+", action="append", default=[], metavar="NAME KEY=VALUE",
                        help="an edge variant: its name and the edges.* parameters it changes")
    parser.add_argument("--results", type=Path, help="results*.json of bench/real_lmo.py: score its estimates too")
    args = parser.parse_args(argv)
    params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    variants = dict([("given", {}), *(variant(v) for v in args.variant)])
    camera = Camera.load(LMO / "camera.json")
    targets = load_targets(LMO)
    frames = sorted({t.frame for t in targets})[: args.frames]
    images = {f: cv2.imread(str(LMO / "rgb" / f"{f:06d}.png"), cv2.IMREAD_COLOR) for f in frames}
    if args.render:
        meshes = scene_meshes()
        images = {f: render(camera, [Placed(meshes[t.obj], t.R, t.t) for t in targets if t.frame == f],
                            background=RENDER_BACKGROUND, color=True).image for f in frames}
    estimates = {}
    if args.results:
        estimates = {(r["obj"], r["frame"]): r for r in json.loads(args.results.read_text()) if r["R"] is not None}
    graphs = {obj: graph_of(obj, args.step_deg) for obj in NAMES}
    rows, density, seconds = [], {name: [] for name in variants}, {name: [] for name in variants}
    for name, changes in variants.items():
        edge_params = params.with_flat(changes).edges
        frame_of = {}
        for f in frames:
            started = time.perf_counter()
            edges = detect_edges(images[f], edge_params)
            seconds[name].append(time.perf_counter() - started)
            frame_of[f] = Frame.of(edges, camera)
            density[name].append(float(np.mean(edges.edge_map > 0)))
        for obj, graph in graphs.items():
            for target in (t for t in targets if t.obj == obj and t.frame in frame_of):
                seen = frame_of[target.frame]
                truth_px = camera.project_model(graph.seg_3d[graph.visible_segments(target.R, target.t)],
                                                target.R, target.t)
                shares = seen.evidence.shares(truth_px, params.pose.inlier_pixels, params.pose.min_margin_pixels,
                                              seen_tolerance_px=params.pose.seen_pixels)
                truth = float(pose_scores(graph, target.R[None], target.t[None], seen, params.pose)[0])
                row = dict(variant=name, obj=obj, frame=target.frame, truth=truth, confirmed=shares.confirmed,
                           support=support(seen.evidence, truth_px, params.pose.inlier_pixels))
                estimate = estimates.get((obj, target.frame))
                if estimate is not None and not estimate["correct"]:
                    R, t = np.array(estimate["R"]).reshape(1, 3, 3), np.array(estimate["t"])[None]
                    row["wrong"] = float(pose_scores(graph, R, t, seen, params.pose)[0])
                rows.append(row)
    report(rows, variants, density, seconds, args)
    return 0


def report(rows: list[dict], variants: dict, density: dict, seconds: dict, args) -> None:
    source = "renders" if args.render else "photos"
    print(f"\nLM-O, the first {args.frames} frames' {len({(r['obj'], r['frame']) for r in rows})} targets, "
          f"{source}, at the true poses; medians support / confirmed beyond chance / truth score")
    print("| object | " + " | ".join(variants) + " |")
    print("|---|" + "---|" * len(variants))
    for obj in [*NAMES, None]:
        cells = []
        for name in variants:
            mine = [r for r in rows if r["variant"] == name and (obj is None or r["obj"] == obj)]
            cells.append(" / ".join(f"{np.median([r[k] for r in mine]):.2f}"
                                    for k in ("support", "confirmed", "truth")))
        print(f"| {NAMES[obj] if obj else '**all**'} | " + " | ".join(cells) + " |")
    print("| edge pixels, share of the image | " + " | ".join(
        f"{100 * np.mean(density[name]):.1f} %" for name in variants) + " |")
    print("| edge stage, median s per image | " + " | ".join(
        f"{np.median(seconds[name]):.3f}" for name in variants) + " |")
    if any("wrong" in r for r in rows):
        cells = []
        for name in variants:
            wrong = [r for r in rows if r["variant"] == name and "wrong" in r]
            cells.append(f"{sum(r['wrong'] >= r['truth'] for r in wrong)} of {len(wrong)} "
                         f"({np.median([r['wrong'] for r in wrong]):.2f})")
        print(f"| fooled: {args.results.name}'s wrong estimates >= truth (their median score) | "
              + " | ".join(cells) + " |")


if __name__ == "__main__":
    sys.exit(main())
