"""brepose-eval: run the estimator over a scene folder and report CONVENTIONS.md metrics."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2

from ..aspect_graph import AspectGraph
from ..offline.cad import load_step, tessellate
from ..online.estimator import Estimator
from ..evaluation.metrics import (ModelPoints, evaluate_scene, format_summary, found_correct, plot_evaluation,
                                  prediction_entry, scene_summary, write_predictions)
from ..evaluation.overlay import draw_overlay
from ..params import EstimatorParams
from ..scene_folder import load_scene
from .common import ArgumentParser, non_negative_int, run


EXAMPLE = """example:
  brepose-render my_part.step renders --n 8 && brepose-compile my_part.step -o my_part.brepose.npz
  brepose-eval renders --graph my_part.brepose.npz --out renders_eval
  (prints one line per image, '7 of 8 found, 6 correct (75 %)' and the metrics of CONVENTIONS.md; correct =
  rotation < 5 degrees and translation < 5 % of the diameter)"""


def parse_args(argv=None):
    parser = ArgumentParser(prog="brepose-eval", description=__doc__, epilog=EXAMPLE)
    parser.add_argument("scene", help="scene folder (camera.json, model.step, images/, gt.json)")
    parser.add_argument("--graph", required=True, help="compiled aspect graph of the scene's part")
    parser.add_argument("--params", help="estimator YAML (config/estimator.yaml layout)")
    parser.add_argument("--out", help="folder for predictions.json, metrics.json, plots and overlays")
    parser.add_argument("--overlays", type=non_negative_int, default=6, help="overlay images to write (default 6)")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)

    def job():
        scene = load_scene(args.scene)
        graph = AspectGraph.load(args.graph)
        params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
        estimator = Estimator(graph, params)
        mesh = tessellate(load_step(scene.step))
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        out = Path(args.out) if args.out else None
        if out:
            (out / "overlays").mkdir(parents=True, exist_ok=True)

        def report(image, result):
            e, err = result.estimate, result.errors
            state = (f"rot {err.rotation_deg:6.2f} deg  trans {err.translation_mm:7.2f} mm  er {err.error_rate:.4f}"
                     if err else "not found")
            print(f"{result.image}: {state}  score {e.score:.2f}  error ratio {e.error_ratio:.2f}  "
                  f"{e.timings.get('total', 0) * 1000:.0f} ms")
            if out and len(list((out / "overlays").iterdir())) < args.overlays:
                cv2.imwrite(str(out / "overlays" / Path(result.image).name), draw_overlay(image, e, result.image))

        results = evaluate_scene(scene, estimator, model, on_image=report)
        estimator.close()
        summary = scene_summary(results)
        print(f"{found_correct([r.errors for r in results])} (model diameter {model.diameter * 1000:.1f} mm)")
        print(format_summary(summary))
        if out:
            write_predictions(out / "predictions.json", [prediction_entry(r.image, r.estimate) for r in results])
            (out / "metrics.json").write_text(json.dumps(
                {"summary": summary, "images": [{"image": r.image, "score": r.estimate.score,
                                                 "errors": r.errors.to_dict() if r.errors else None}
                                                for r in results]}, indent=1) + "\n")
            plot_evaluation(results, out / "evaluation.png", model.diameter, Path(args.scene).name)
            print(f"wrote predictions, metrics, evaluation.png and overlays to {out}")

    return run(job)


if __name__ == "__main__":
    sys.exit(main())
