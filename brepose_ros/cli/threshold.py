"""brepose-threshold: choose pose.min_score for a part from a precision/recall run on renders.

Renders N clean images of the part and N off-centre ones with 30 % of it hidden among
clutter (a detection there is correct when the pose succeeds: rotation < 5 degrees,
translation < 5 % of the diameter), and N clean images of each part of --others, where any
detection is wrong. The part's estimator runs on all of them; for each threshold on the score,
precision = correct detections / all detections and recall = correct detections / images of
the part. Prints the table, the same for the confidence (pose.min_confidence), and the
lowest min_score whose precision reaches --precision, and writes that min_score (with
pose.min_confidence 0: the score alone decides, as measured) into an estimator parameter
file for brepose-estimate --params and the node.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from ..aspect_graph import AspectGraph
from ..evaluation.metrics import ModelPoints, calibrate_min_score, evaluate_scene, percent, precision_recall
from ..offline.cad import load_step, tessellate
from ..online.estimator import Estimator
from ..params import EstimatorParams
from ..synthetic.scenes import SceneConfig, generate_scene
from .common import ArgumentParser, fraction, non_negative_int, positive_int, run
from .render import BUILTIN_PREFIX, model_step

EXAMPLE = """example:
  brepose-threshold my_part.step --graph my_part.brepose.npz --others builtin:box sibling.step -o my_part.yaml
  brepose-estimate --graph my_part.brepose.npz --params my_part.yaml ...
  (list look-alike parts in --others: they are what the score must tell apart)"""
#: the part's own scenes: as it is usually seen, and partly hidden among other shapes
POSITIVES = {"clean": SceneConfig(), "30 % occluded among clutter": SceneConfig(offcenter=True, occlusion=0.3,
                                                                                  clutter=3)}
DEFAULT_OTHERS = [f"{BUILTIN_PREFIX}{name}" for name in ("cube", "cylinder", "sample_bracket")]
#: the rows of the printed table
THRESHOLDS = np.round(np.arange(0.3, 1.0, 0.05), 2)
CONFIDENCES = np.round(np.arange(0.1, 1.0, 0.1), 2)


def parse_args(argv=None):
    p = ArgumentParser(prog="brepose-threshold", description=__doc__.splitlines()[0], epilog=EXAMPLE)
    p.add_argument("part", help=f"STEP file of the part the graph was compiled from, or {BUILTIN_PREFIX}NAME")
    p.add_argument("--graph", required=True, help="the part's aspect graph (.brepose.npz)")
    p.add_argument("--others", nargs="+", default=DEFAULT_OTHERS, metavar="STEP",
                   help=f"parts that are not yours: STEP files or {BUILTIN_PREFIX}NAME (default: "
                        f"{' '.join(DEFAULT_OTHERS)})")
    p.add_argument("--n", type=positive_int, default=12, help="images per scene (default 12)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed of the scenes (default 0)")
    p.add_argument("--precision", type=fraction, default=1.0,
                   help="precision min_score must reach (default 1: no wrong detection among the renders)")
    p.add_argument("--params", help="estimator YAML to start from (its min_score and min_confidence are replaced)")
    p.add_argument("-o", "--output", type=Path, help="estimator YAML to write with the chosen min_score")
    p.add_argument("--scenes", type=Path, help="folder to keep the rendered scenes in (default: a temporary one)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)

    def job() -> int:
        base = EstimatorParams.load(args.params) if args.params else EstimatorParams()
        # every pose scored, found or not: the threshold is what this run chooses
        estimator = Estimator(AspectGraph.load(args.graph),
                              base.with_flat({"pose.min_score": 0.0, "pose.min_confidence": 0.0}))
        with tempfile.TemporaryDirectory() as tmp:
            folder = args.scenes or Path(tmp)
            folder.mkdir(parents=True, exist_ok=True)
            step = model_step(args.part, folder)
            scenes = [(generate_scene(step, folder / f"part_{i}", args.n, args.seed + i, config), True)
                      for i, config in enumerate(POSITIVES.values())]
            scenes += [(generate_scene(model_step(other, folder), folder / f"other_{i}", args.n, args.seed), False)
                       for i, other in enumerate(args.others)]
            scores, confidences, correct = [], [], []
            with tqdm(total=args.n * len(scenes), unit="image", disable=args.quiet, desc="estimating") as bar:
                for scene, positive in scenes:
                    mesh = tessellate(load_step(scene.step))
                    model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
                    for result in evaluate_scene(scene, estimator, model, on_image=lambda *_: bar.update(1)):
                        scores.append(result.estimate.score)
                        confidences.append(result.estimate.confidence)
                        correct.append(positive and bool(result.errors and result.errors.success))
        estimator.close()
        n_part = args.n * len(POSITIVES)
        precision, recall, detections = precision_recall(scores, correct, n_part, THRESHOLDS)
        print(f"{n_part} images of the part ({', '.join(POSITIVES)}), {len(scores) - n_part} images of other parts "
              f"({' '.join(args.others)})\n\n| min_score | detections | precision | recall |\n|---|---|---|---|")
        for row in zip(THRESHOLDS, detections, precision, recall):
            print("| {:.2f} | {} | {:.2f} | {:.2f} |".format(*row))
        print_confidence(confidences, correct, n_part, args.precision)
        lowest_kept = calibrate_min_score(scores, correct, args.precision)
        if lowest_kept is None:
            print(f"\nno threshold reaches precision {args.precision:g}: the part's right poses score no higher "
                  f"than its wrong ones or the other parts' (see docs/tutorial.md, 'When the part is not found')")
            return 1
        # halfway to the highest score left out, not on a measured score: new images vary
        scores, correct = np.asarray(scores), np.asarray(correct)
        left_out = scores[scores < lowest_kept]
        chosen = round(float((lowest_kept + left_out.max()) / 2 if len(left_out) else lowest_kept), 3)
        found = scores >= chosen
        right, wrong = int((found & correct).sum()), int((found & ~correct).sum())
        print(f"\nmin_score {chosen:.3f}: {right} of {n_part} images of the part found at the right pose "
              f"({percent(right, n_part)}), {wrong} wrong detections")
        if args.output:
            command = " ".join(["brepose-threshold", *(sys.argv[1:] if argv is None else argv)])
            write_params(args.output, base.with_flat({"pose.min_score": chosen, "pose.min_confidence": 0.0}), command)
            print(f"wrote {args.output}")
        return 0

    return run(job)


def print_confidence(confidences, correct, n_part: int, target: float) -> None:
    """The same table for the confidence (the probability that the pose is right,
    online/confidence.py), and the pose.min_confidence that reaches the precision."""
    precision, recall, detections = precision_recall(confidences, correct, n_part, CONFIDENCES)
    print("\nthe same against the confidence (pose.min_confidence, with pose.min_score 0):\n\n"
          "| min_confidence | detections | precision | recall |\n|---|---|---|---|")
    for row in zip(CONFIDENCES, detections, precision, recall):
        print("| {:.2f} | {} | {:.2f} | {:.2f} |".format(*row))
    lowest = calibrate_min_score(confidences, correct, target)
    if lowest is not None:
        (p,), (r,), _ = precision_recall(confidences, correct, n_part, [lowest])
        print(f"\nmin_confidence {lowest:.3f} reaches precision {p:.2f} with recall {r:.2f}")


def write_params(path: Path, params: EstimatorParams, command: str) -> None:
    """The parameters that differ from the defaults, and min_score, as estimator YAML."""
    defaults = EstimatorParams().flat()
    nested: dict[str, dict] = {}
    for name, value in params.flat().items():
        if value != defaults[name] or name == "pose.min_score":
            group, _, key = name.partition(".")
            nested.setdefault(group, {})[key] = value
    path.write_text(f"# written by {command}\n" + yaml.safe_dump(nested))


if __name__ == "__main__":
    sys.exit(main())
