"""Does the look across a pose's silhouette tell right poses from wrong ones, where the edges
do not? Region cues beside the edge score: at the right pose the part's outline separates
two looks, while a shrunken copy lying on the part's own edges has part on both sides; and
at the right pose the part's surface normals explain the shading over its silhouette.

    python bench/silhouette_contrast.py [--n 16] [--start 64] [--parts sharp_bracket ...]
                                        [--conditions clean clutter occl30+clutter] [--label NAME]

For each image of bench/accuracy.py's cached scenes, the estimator with default parameters;
the refinement's finalists (``PoseRefiner.finalists``, captured), the final pose and the
truth refined and polished (``occlusion_diagnosis.refined_truth``) are each scored by the
edges (score, evidence in nats), by the *contrast* of their silhouette: 1 - the
Bhattacharyya coefficient of the colour histograms of two bands along it, inside and outside
(``band_contrast``), and by the *shading fit* (``online.appearance.shading_fit``: how much of the grey level
over the mesh's silhouette at the pose its normals explain under some distant light, the
spherical harmonics up to order 2, outliers such as an occluder trimmed). The silhouette is
the part's mesh filled at the pose (as the graph's surface now holds it) or the convex hull of
the pose's projected visible edges (what the edges alone could draw). Prints, per cue: how
often the refined truth beats a wrong found pose, how often a right found pose beats the
wrong finalists of its image, and the AUC of right against wrong found poses; then the cues
combined with the estimator's confidence in a logistic model fitted with one part left out
and applied to it (``combined_tables``). Records go to
data/bench/results/silhouette_contrast_LABEL.json; ``--from-records`` prints the tables again
from such files.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.stats import mannwhitneyu

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import PARTS, add_scene_arguments, bench_steps, distractor_meshes, scene  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from bench.occlusion_diagnosis import refined_truth  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.camera import Camera  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors  # noqa: E402
from brepose_ros.offline.cad import Mesh, load_step, tessellate  # noqa: E402
from brepose_ros.online.appearance import shading_fit  # noqa: E402
from brepose_ros.online.confidence import Logistic  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.scoring import pose_surprises, visible_rows  # noqa: E402

#: each band is this share of the part's projected size wide, and at least MIN_BAND_PX
BAND_SHARE = 0.06
MIN_BAND_PX = 3.0
CUES = ("score", "nats", "contrast_mesh", "contrast_hull", "shading_fit")
#: the cue sets combined with the confidence (``combined_tables``)
COMBINED = (("confidence",), ("confidence", "nats"), ("confidence", "contrast_mesh"), ("confidence", "shading_fit"),
            ("confidence", "nats", "contrast_mesh", "shading_fit"))


def mesh_silhouette(mesh: Mesh, R: np.ndarray, t: np.ndarray, camera: Camera) -> np.ndarray | None:
    """The part's silhouette at the pose, (H, W) uint8 0/1; None if any vertex is behind the camera."""
    points = mesh.vertices @ R.T + t
    if np.any(points[:, 2] <= 1e-4):
        return None
    triangles = np.round(camera.project(points)[mesh.triangles] * 4).astype(np.int32)  # 2 fractional bits
    mask = np.zeros((camera.height, camera.width), np.uint8)
    for triangle in triangles:  # one call per triangle: fillPoly's even-odd rule would cut overlaps out
        cv2.fillConvexPoly(mask, triangle, 1, shift=2)
    return mask


def edge_hull(graph: AspectGraph, R: np.ndarray, t: np.ndarray, camera: Camera) -> np.ndarray | None:
    """The convex hull of the pose's projected visible model edges, (H, W) uint8 0/1."""
    rows, _ = visible_rows(graph, R[None], t[None])
    points = graph.seg_3d[rows].reshape(-1, 3) @ R.T + t
    if np.any(points[:, 2] <= 1e-4):
        return None
    hull = cv2.convexHull(camera.project(points).astype(np.float32))
    mask = np.zeros((camera.height, camera.width), np.uint8)
    cv2.fillPoly(mask, [np.round(hull * 4).astype(np.int32)], 1, shift=2)
    return mask


def quantised(image: np.ndarray) -> tuple[np.ndarray, int]:
    """Each pixel's histogram bin and the number of bins: 8 levels a colour channel, 32 grey levels."""
    if image.ndim == 2:
        return (image.astype(np.int32) * 32) // (int(np.iinfo(image.dtype).max) + 1), 32
    q = (image.astype(np.int32) * 8) // (int(np.iinfo(image.dtype).max) + 1)
    return (q[..., 0] * 8 + q[..., 1]) * 8 + q[..., 2], 512


def band_contrast(bins: np.ndarray, n_bins: int, mask: np.ndarray | None, band_px: float) -> float:
    """1 - the Bhattacharyya coefficient of the histograms of the bands ``band_px`` wide inside
    and outside the mask's outline: 0 where both look alike, 1 where they share no bin; NaN
    without a mask or a band of 10 pixels."""
    if mask is None:
        return float("nan")
    inside = (mask > 0) & (cv2.distanceTransform(mask, cv2.DIST_L2, 3) <= band_px)
    outside = (mask == 0) & (cv2.distanceTransform(1 - mask, cv2.DIST_L2, 3) <= band_px)
    if inside.sum() < 10 or outside.sum() < 10:
        return float("nan")
    h_in = np.bincount(bins[inside], minlength=n_bins) / inside.sum()
    h_out = np.bincount(bins[outside], minlength=n_bins) / outside.sum()
    return float(1.0 - np.sum(np.sqrt(h_in * h_out)))


def auc(values: np.ndarray, right: np.ndarray) -> float:
    """The probability that a right pose's value exceeds a wrong one's (ties half)."""
    ok = ~np.isnan(values)
    values, right = values[ok], right[ok]
    return float(mannwhitneyu(values[right], values[~right]).statistic / (right.sum() * (~right).sum()))


def tables(images: list[dict]) -> None:
    """The three comparisons of the module doc, per cue."""
    finals = [(r, next(p for p in r["poses"] if p["kind"] == "final")) for r in images if r["found"]]
    right = np.array([f["right"] for _, f in finals])
    print(f"{len(images)} images, {len(finals)} found, {right.sum()} right\n")
    print("| cue | truth beats a wrong found pose | right found pose beats a wrong finalist "
          "| AUC right vs wrong found |")
    print("|---|---|---|---|")
    for cue in CUES:
        truth_wins = pairs = final_wins = finalist_pairs = 0
        for r, final in finals:
            truth = next(p for p in r["poses"] if p["kind"] == "truth")
            if not final["right"] and truth["right"]:
                pairs += 1
                truth_wins += truth[cue] > final[cue]
            if final["right"]:
                for p in r["poses"]:
                    if p["kind"] == "finalist" and not p["right"]:
                        finalist_pairs += 1
                        final_wins += final[cue] > p[cue]
        values = np.array([f[cue] for _, f in finals], float)
        print(f"| {cue} | {truth_wins} of {pairs} | {final_wins} of {finalist_pairs} | {auc(values, right):.2f} |")


def combined_tables(images: list[dict]) -> None:
    """Can the cues, combined with the estimator's confidence, tell right found poses from
    wrong ones on parts they were not fitted on? Per cue set, a logistic model fitted on every
    part but one and applied to that one (leave one part out): the AUC of right against wrong
    found poses, and how many right poses the most confident keep while at least 95 % of those
    kept are right."""
    finals = [(r["part"], next(p for p in r["poses"] if p["kind"] == "final")) for r in images if r["found"]]
    parts = np.array([part for part, _ in finals])
    right = np.array([f["right"] for _, f in finals])
    print(f"\nCombined with the confidence, leave one part out ({len(finals)} found poses, {right.sum()} right)")
    print("| cues | AUC right vs wrong found | right kept at 95 % precision |")
    print("|---|---|---|")
    for cues in COMBINED:
        X = np.nan_to_num(np.array([[f[c] for c in cues] for _, f in finals], float))
        predicted = np.zeros(len(finals))
        for part in np.unique(parts):
            fit = parts != part
            # lightly ridged: 0.01 on the summed log-loss, as the figures of verification.md were made
            predicted[~fit] = Logistic.fit(X[fit], right[fit], l2=0.01 / fit.sum()).logit(X[~fit])
        kept_right = np.cumsum(right[np.argsort(-predicted)])
        precise = kept_right / np.arange(1, len(right) + 1) >= 0.95
        print(f"| {' + '.join(cues)} | {auc(predicted, right):.2f} | "
              f"{kept_right[np.flatnonzero(precise)[-1]] if precise.any() else 0} of {right.sum()} |")


def records(args) -> list[dict]:
    """Every image's poses with their cues (module doc)."""
    cache = REPO / "data" / "bench"
    distractors = distractor_meshes(cache)
    out = []
    for name, step in bench_steps(args.parts, cache).items():
        graph = AspectGraph.load(cached_graph_path(step, cache, 5.0))
        mesh = tessellate(load_step(step))
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        estimator = Estimator(graph)
        p = estimator.params
        captured: list = []
        finalists = estimator._refiner.finalists

        def capture(*a, **k):
            captured[:] = finalists(*a, **k)
            return captured[:]

        estimator._refiner.finalists = capture
        for condition in args.conditions:
            cached = scene(cache, name, step, condition, range(args.start, args.start + args.n), distractors)
            camera = cached.camera
            for i, entry in enumerate(cached.entries, start=args.start):
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                captured.clear()
                frame = estimator.part_frame(image, camera)  # the edges once, for the estimate and the cues
                est = estimator.estimate(image, camera, frame=frame)
                truth = refined_truth(estimator, frame, entry)
                poses = [("finalist", c.score, c.R, c.t) for c in captured]
                if est.found:
                    poses.append(("final", est.score, est.R, est.t))
                poses.append(("truth", truth.score, truth.R, truth.t))
                nats = pose_surprises(graph, np.array([x[2] for x in poses]), np.array([x[3] for x in poses]),
                                      frame, p.pose)
                bins, n_bins = quantised(image)
                grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
                described = []
                for (kind, score, R, t), n in zip(poses, nats):
                    depth = float((R @ graph.model_center + t)[2])
                    band = max(MIN_BAND_PX, BAND_SHARE * graph.model_diameter * camera.focal / max(depth, 1e-6))
                    described.append({
                        "kind": kind, "score": float(score), "nats": float(n),
                        "right": bool(pose_errors(R, t, entry.R, entry.t, model, graph).success_sym),
                        "contrast_mesh": band_contrast(bins, n_bins, mesh_silhouette(mesh, R, t, camera), band),
                        "contrast_hull": band_contrast(bins, n_bins, edge_hull(graph, R, t, camera), band),
                        "shading_fit": shading_fit(grey, mesh, R, t, camera)})
                if est.found:
                    next(d for d in described if d["kind"] == "final")["confidence"] = float(est.confidence)
                out.append({"part": name, "condition": condition, "image": i, "found": bool(est.found),
                            "poses": described})
                print(f"{name} {condition} {i}: {len(described)} poses", flush=True)
        estimator.close()
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=16, parts=list(PARTS), conditions=["clean", "clutter", "occl30+clutter"], start=True)
    parser.add_argument("--label", default="default")
    parser.add_argument("--from-records", nargs="*", type=Path, help="print the tables of saved records only")
    args = parser.parse_args(argv)
    if args.from_records:
        images = [r for path in args.from_records for r in json.loads(path.read_text())["images"]]
    else:
        images = records(args)
        out = REPO / "data" / "bench" / "results" / f"silhouette_contrast_{args.label}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"images": images}) + "\n")
        print(f"wrote {out}", file=sys.stderr)
    tables(images)
    if all("confidence" in p for r in images if r["found"] for p in r["poses"] if p["kind"] == "final"):
        combined_tables(images)
    return 0


if __name__ == "__main__":
    sys.exit(main())
