"""brepose-estimate: find the part in images, write the predictions JSON of CONVENTIONS.md."""
from __future__ import annotations

import sys
from pathlib import Path

import cv2

from ..aspect_graph import AspectGraph
from ..camera import Camera
from ..evaluation.metrics import percent, prediction_entry, write_predictions
from ..evaluation.overlay import draw_overlay
from ..image_codec import read_image_file
from ..online.estimator import Estimator, not_found_reason
from ..params import EstimatorParams
from .common import ArgumentParser, run

EXAMPLE = """example:
  brepose-estimate --graph my_part.brepose.npz --camera camera.json photos/*.png -o poses.json --overlays checks
  (prints one line per image and '3 of 4 found (75 %)'; checks/ gets each photo with the model's edges drawn at
  the estimated pose: green found, red not found)"""


def parse_args(argv=None):
    parser = ArgumentParser(prog="brepose-estimate", description=__doc__, epilog=EXAMPLE)
    parser.add_argument("images", nargs="+", help="image files (8-bit grey or BGR)")
    parser.add_argument("--graph", required=True, help="compiled aspect graph (.brepose.npz)")
    parser.add_argument("--camera", required=True, help="camera.json with the intrinsics")
    parser.add_argument("--params", help="estimator YAML (config/estimator.yaml layout)")
    parser.add_argument("-o", "--output", required=True, help="predictions JSON to write")
    parser.add_argument("--overlays", type=Path, metavar="DIR",
                        help="folder for each image with the model edges drawn at the estimated pose (PNG)")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)

    def job():
        params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
        estimator = Estimator(AspectGraph.load(args.graph), params)
        camera = Camera.load(args.camera)
        if args.overlays:
            args.overlays.mkdir(parents=True, exist_ok=True)
        predictions = []
        for path in args.images:
            image = read_image_file(path)
            estimate = estimator.estimate(image, camera)
            predictions.append(prediction_entry(path, estimate))
            measures = f"score {estimate.score:.2f}, confidence {estimate.confidence:.2f}" + (
                f", shading fit {estimate.shading_fit:.2f}" if estimate.shading_fit is not None else "")
            state = measures if estimate.found else f"not found ({not_found_reason(estimate, estimator.params.pose)})"
            if estimate.found and estimate.ambiguous:
                state += f", ambiguous: the image cannot tell it from a symmetric twin (margin " \
                         f"{estimate.symmetry_margin:.2f})"
            if estimate.skipped:
                state += f", time budget spent before: {', '.join(estimate.skipped)}"
            print(f"{path}: {state}, error ratio {estimate.error_ratio:.2f}, "
                  f"{estimate.timings.get('total', 0) * 1000:.0f} ms", file=sys.stderr)
            if args.overlays:
                overlay = args.overlays / f"{Path(path).stem}.png"
                if not cv2.imwrite(str(overlay), draw_overlay(image, estimate, Path(path).name)):
                    raise OSError(f"cannot write {overlay}")
        estimator.close()
        write_predictions(args.output, predictions)
        found = sum(p["R"] is not None for p in predictions)
        print(f"{found} of {len(predictions)} found ({percent(found, len(predictions))}); "
              f"wrote {args.output}" + (f" and overlays in {args.overlays}" if args.overlays else ""))

    return run(job)


if __name__ == "__main__":
    sys.exit(main())
