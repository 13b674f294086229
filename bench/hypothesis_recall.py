"""Hypothesis recall of the generators: the share of images where some candidate handed to
the view climb (``Estimator.candidates``: hypotheses refined and scored) lies near the true
pose, per generator setting, with the final success and the time per image.

    python bench/hypothesis_recall.py [--n 12] [--parts sharp_bracket ...] [--conditions clean ...]
        [--variant LABEL[:group.key=value,...] ...] [--known-size RATIO]

A variant is a label and flat parameter overrides; a label naming a generator setting
(``tetrad``, ``search``, ``both``, ``seeded+tetrad``, ...) sets ``search.generators``.
Default: tetrad, search, both. Near means within ``NEAR_DEG`` of the truth in rotation and
``NEAR_CENTRE`` part diameters in the 3D position of the model centre, both against the
pose equivalent to the truth under the part's exact symmetries that is nearest the
candidate (``metrics.symmetric_truth``). Columns per variant: recall (a near candidate
exists), first (the best-scored candidate is near), success (the estimator's final pose:
climb, polish, rival and twin checks, the ``pose.min_score`` floor; CONVENTIONS.md success up to
the part's exact symmetries, as *near* is), and median
milliseconds of the candidates (``gen ms``) and of the whole image after edges (``all ms``).
Scenes are those of bench/accuracy.py (varied look, seed 100, cached in data/bench).
``--known-size RATIO`` sets every variant's search sizes, image by image, to the part's true
projected diameter divided and multiplied by RATIO (``search.min_size_fraction`` /
``max_size_fraction``): the search's half of a known working distance alone (users set
``pose.min_distance`` / ``max_distance``, which also drop poses outside the range:
bench/known_distance.py measures that).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import (CONDITIONS, SPAN, add_scene_arguments, bench_steps, distractor_meshes,  # noqa: E402
                            graph_and_model, part_set, scene, scene_path)
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors, symmetric_truth  # noqa: E402
from brepose_ros.geometry import rotation_angle_deg  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.image_edges import detect_edges  # noqa: E402
from brepose_ros.online.symmetry import check_twins  # noqa: E402
from brepose_ros.online.workers import SERIAL  # noqa: E402
from brepose_ros.params import GENERATORS, EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

#: a candidate this near the truth is one the climb and polish can finish (brief of issue 11)
NEAR_DEG, NEAR_CENTRE = 15.0, 0.10


def variant_params(spec: str) -> tuple[str, EstimatorParams]:
    label, _, overrides = spec.partition(":")
    flat = dict(o.split("=", 1) for o in overrides.split(",") if o)
    if label == "both" or all(stage in GENERATORS for stage in label.split("+")):
        flat.setdefault("search.generators", label)
    defaults = EstimatorParams().flat()
    unknown = set(flat) - set(defaults)
    if unknown:
        raise SystemExit(f"error: unknown parameter(s) {', '.join(sorted(unknown))}")
    return label, EstimatorParams().with_flat({k: type(defaults[k])(v) for k, v in flat.items()})


def near_truth(R, t, entry, graph) -> bool:
    R_true, t_true = symmetric_truth(R, entry.R, entry.t, graph)
    centre = np.linalg.norm(R @ graph.model_center + t - (R_true @ graph.model_center + t_true))
    return bool(rotation_angle_deg(R, R_true) < NEAR_DEG and centre < NEAR_CENTRE * graph.model_diameter)


def chosen_pose(estimator: Estimator, candidates: list, frame: Frame, p: EstimatorParams, rivals: bool = True):
    """The pose ``Estimator.estimate`` chooses among refined ``candidates`` before the twin
    check (``Estimator.choose``); without ``rivals`` the best climbed pose, polished, as
    before the rival check (main cb60954)."""
    if not rivals:
        return estimator._refiner.best(candidates, frame, p.pose)
    return estimator.choose(frame, candidates, p, SERIAL)


def measure(estimator: Estimator, frame: Frame, entry, model: ModelPoints) -> dict:
    """Recall, first, success and times of one variant on one image."""
    g, p = estimator.graph, estimator.params
    start = time.perf_counter()
    stages: dict[str, float] = {}
    candidates = estimator.candidates(frame, stages)
    generated = time.perf_counter()
    near = [near_truth(c.R, c.t, entry, g) for c in candidates]
    success = False
    if candidates:
        best = chosen_pose(estimator, candidates, frame, p)
        if p.pose.twin_check:
            best = check_twins(best, g, estimator._refiner, frame, p.pose).pose
        success = best.score >= p.pose.min_score and pose_errors(best.R, best.t, entry.R, entry.t, model, g).success_sym
    done = time.perf_counter()
    first = bool(candidates) and near[int(np.argmax([c.score for c in candidates]))]
    return {"recall": any(near), "first": first, "success": success, "count": len(candidates),
            "best_score": max((c.score for c in candidates), default=0.0),
            "gen_ms": 1000 * (generated - start), "all_ms": 1000 * (done - start),
            "stages": " ".join(f"{k} {1000 * v:.0f}" for k, v in stages.items())}


def known_size(params: EstimatorParams, graph, camera, entry, ratio: float) -> EstimatorParams:
    """``params`` with the search's sizes within ``ratio`` of the part's projected diameter in this image."""
    size = camera.focal * graph.model_diameter / np.linalg.norm(entry.R @ graph.model_center + entry.t)
    low = size / ratio / np.hypot(camera.width, camera.height)
    return dataclasses.replace(params, search=dataclasses.replace(params.search, min_size_fraction=low,
                                                                  max_size_fraction=low * ratio * ratio))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=12, parts=["sharp_bracket", "base_attachment"],
                        conditions=["clean", "occl30+clutter"], start=True)
    parser.add_argument("--variant", nargs="*", default=["tetrad", "search", "both"])
    parser.add_argument("--span", type=float, nargs=2, default=SPAN, metavar=("LOW", "HIGH"),
                        help="the part's projected size, share of the image's smaller side (bench/accuracy.py's)")
    parser.add_argument("--known-size", type=float, default=0.0, metavar="RATIO",
                        help="search only sizes within this ratio of the part's true size (0: the parameters')")
    parser.add_argument("--verbose", action="store_true", help="a line per image")
    args = parser.parse_args(argv)
    variants = [variant_params(spec) for spec in args.variant]
    cache = REPO / "data" / "bench"
    distractors = None
    rows = []
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimators = [(label, Estimator(graph, params)) for label, params in variants]
        for condition in args.conditions:
            folder = scene_path(cache, name, condition, span=tuple(args.span))
            images = range(args.start, args.start + args.n)
            cached_count = len(load_scene(folder).entries) if (folder / "gt.json").exists() else 0
            if cached_count < images.stop and distractors is None:  # the scene must be grown
                distractors = distractor_meshes(cache)
            cached = scene(cache, name, step, condition, images, distractors, span=tuple(args.span))
            results = {label: [] for label, _ in estimators}
            for entry in cached.entries:
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                frame = Frame.of(detect_edges(image, variants[0][1].edges), cached.camera)
                # alternate the order of variants from image to image: the machine is shared
                turn = len(results[estimators[0][0]])
                order = estimators[turn % len(estimators):] + estimators[:turn % len(estimators)]
                for label, estimator in order:
                    if args.known_size:
                        estimator.params = known_size(dict(variants)[label], graph, cached.camera, entry,
                                                      args.known_size)
                    r = measure(estimator, frame, entry, model)
                    results[label].append(r)
                    if args.verbose:
                        print(f"{name} {condition} {entry.image} {label}: recall={r['recall']} first={r['first']} "
                              f"success={r['success']} n={r['count']} best={r['best_score']:.2f} "
                              f"gen={r['gen_ms']:.0f} ms ({r['stages']})", flush=True)
            for label, _ in estimators:
                rows.append((part_set(name), name, condition, label, results[label]))
                print_row(rows[-1])
        for _, estimator in estimators:
            estimator.close()
    print_tables(rows)
    return 0


def print_row(row) -> None:
    part_set_name, name, condition, label, images = row
    print(f"  {name} {condition} {label}: " + cells(images), file=sys.stderr, flush=True)


def cells(images: list[dict]) -> str:
    n = max(len(images), 1)
    return (f"{sum(i['recall'] for i in images) / n:.2f} | {sum(i['first'] for i in images) / n:.2f} | "
            f"{sum(i['success'] for i in images) / n:.2f} | {np.median([i['gen_ms'] for i in images]):.0f} | "
            f"{np.median([i['all_ms'] for i in images]):.0f}")


def print_tables(rows) -> None:
    print("\n| set | part | condition | variant | images | recall | first | success | gen ms | all ms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for part_set_name, name, condition, label, images in rows:
        print(f"| {part_set_name} | {name} | {condition} | {label} | {len(images)} | {cells(images)} |")
    print("\nPooled per set and condition: recall | first | success | gen ms | all ms\n")
    print("| set | condition | variant | images | recall | first | success | gen ms | all ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    keys = dict.fromkeys((s, c, v) for s, _, c, v, _ in rows)
    for s, c, v in sorted(keys, key=lambda k: (k[0] != "tune", list(CONDITIONS).index(k[1]))):
        images = [i for s2, _, c2, v2, imgs in rows if (s2, c2, v2) == (s, c, v) for i in imgs]
        print(f"| {s} | {c} | {v} | {len(images)} | {cells(images)} |")


if __name__ == "__main__":
    sys.exit(main())
