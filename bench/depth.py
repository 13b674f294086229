"""Whether the larger-pose check (``pose.larger_check``, ``online/larger.py``) rights the estimator's
wrong poses at the wrong depth, what it breaks, and what it costs.

    python bench/depth.py [--n 8] [--parts sharp_bracket ...] [--conditions clean clutter] [--label NAME]

For each part, condition and image of bench/accuracy.py's cached scenes (varied look, seed
100, 5-degree graphs), the estimator with default parameters, once with the check off and
once on (alternating, so both see the same load). A pose is *right* when it is reported
(score >= ``pose.min_score``) and succeeds up to the part's exact symmetries. Per row:
images, right poses off and on; wrong reported poses with the check off, and of them those
at another depth (the part's centre more than 10 % nearer or farther than the truth's); the
check's rights made and broken; the median time per image off and on and the check's own
median time where it ran. Per-image records go to data/bench/results/depth_LABEL.json.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import (PARTS, add_scene_arguments, bench_steps, distractor_meshes, graph_and_model,  # noqa: E402
                            scene)
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402

#: a wrong pose is at another depth when its centre's distance is this share off the truth's
DEPTH_SAME = 0.1


def outcome(estimator: Estimator, image: np.ndarray, camera, entry, graph: AspectGraph, model: ModelPoints) -> dict:
    """One estimate: reported, right, its centre's distance over the truth's, score and times (ms)."""
    est = estimator.estimate(image, camera)
    out = {"found": est.found, "right": False, "depth": None, "score": est.score,
           "ms": 1000.0 * est.timings["total"], "check_ms": 1000.0 * est.timings.get("larger", 0.0)}
    if est.found:
        out["right"] = bool(pose_errors(est.R, est.t, entry.R, entry.t, model, graph).success_sym)
        out["depth"] = float(np.linalg.norm(est.R @ graph.model_center + est.t)
                             / np.linalg.norm(entry.R @ graph.model_center + entry.t))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=8, parts=list(PARTS), conditions=["clean", "clutter"])
    parser.add_argument("--label", default="default")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    distractors = distractor_meshes(cache)
    records, rows = [], []
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = Estimator(graph)
        base = estimator.params
        settings = {on: dataclasses.replace(base, pose=dataclasses.replace(base.pose, larger_check=on))
                    for on in (False, True)}
        for condition in args.conditions:
            images = scene(cache, name, step, condition, args.n, distractors)
            row = {"part": name, "condition": condition, "images": len(images.entries), "right_off": 0, "right_on": 0,
                   "wrong_off": 0, "other_depth": 0, "made": 0, "broken": 0, "ms_off": [], "ms_on": [],
                   "check_ms": []}
            for i, entry in enumerate(images.entries):
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                result = {}
                for on in ((False, True) if i % 2 == 0 else (True, False)):
                    estimator.params = settings[on]
                    result[on] = outcome(estimator, image, images.camera, entry, graph, model)
                off, on = result[False], result[True]
                records.append({"part": name, "condition": condition, "image": i, "off": off, "on": on})
                row["right_off"] += off["right"]
                row["right_on"] += on["right"]
                wrong = off["found"] and not off["right"]
                row["wrong_off"] += wrong
                row["other_depth"] += wrong and abs(off["depth"] - 1) > DEPTH_SAME
                row["made"] += on["right"] and not off["right"]
                row["broken"] += off["right"] and not on["right"]
                row["ms_off"].append(off["ms"])
                row["ms_on"].append(on["ms"])
                if on["check_ms"]:
                    row["check_ms"].append(on["check_ms"])
                if off["right"] != on["right"] or wrong:
                    print(f"{name} {condition} {i}: off {'right' if off['right'] else 'wrong'} {off['score']:.2f} "
                          f"depth x{off['depth'] or 0:.2f}; on {'right' if on['right'] else 'wrong'} "
                          f"{on['score']:.2f} depth x{on['depth'] or 0:.2f} (check {on['check_ms']:.0f} ms)",
                          flush=True)
            rows.append(row)
            out = cache / "results" / f"depth_{args.label}.json"  # after every row: a killed run keeps its rows
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps({"rows": rows, "images": records}, indent=1, default=float) + "\n")
        estimator.close()
    print("\n| part | condition | images | right: off / on | wrong (off) | of them at another depth | "
          "made / broken | ms per image (median): off / on | check ms (median, where run) |")
    print("|---|---|---|---|---|---|---|---|---|")

    def median(values):
        return f"{np.median(values):.0f}" if values else "-"

    for r in rows:
        print(f"| {r['part']} | {r['condition']} | {r['images']} | {r['right_off']} / {r['right_on']} | "
              f"{r['wrong_off']} | {r['other_depth']} | {r['made']} / {r['broken']} | "
              f"{median(r['ms_off'])} / {median(r['ms_on'])} | {median(r['check_ms'])} |")
    total = {k: sum(r[k] for r in rows) for k in ("images", "right_off", "right_on", "wrong_off", "other_depth",
                                                  "made", "broken")}
    print(f"| **all** | | {total['images']} | {total['right_off']} / {total['right_on']} | {total['wrong_off']} | "
          f"{total['other_depth']} | {total['made']} / {total['broken']} | "
          f"{median([m for r in rows for m in r['ms_off']])} / {median([m for r in rows for m in r['ms_on']])} | "
          f"{median([m for r in rows for m in r['check_ms']])} |")
    print(f"\nwrote {cache / 'results' / f'depth_{args.label}.json'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
