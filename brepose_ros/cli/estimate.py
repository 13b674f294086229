"""brepose-estimate: find the part in images, write the predictions JSON of CONVENTIONS.md."""
from __future__ import annotations

import sys

from ..aspect_graph import AspectGraph
from ..camera import Camera
from ..online.estimator import Estimator
from ..evaluation.metrics import prediction_entry, write_predictions
from ..image_codec import read_image_file
from ..params import EstimatorParams
from .common import ArgumentParser, run


def parse_args(argv=None):
    parser = ArgumentParser(prog="brepose-estimate", description=__doc__)
    parser.add_argument("images", nargs="+", help="image files (8-bit grey or BGR)")
    parser.add_argument("--graph", required=True, help="compiled aspect graph (.brepose.npz)")
    parser.add_argument("--camera", required=True, help="camera.json with the intrinsics")
    parser.add_argument("--params", help="estimator YAML (config/estimator.yaml layout)")
    parser.add_argument("-o", "--output", required=True, help="predictions JSON to write")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)

    def job():
        params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
        estimator = Estimator(AspectGraph.load(args.graph), params)
        camera = Camera.load(args.camera)
        predictions = []
        for path in args.images:
            image = read_image_file(path)
            estimate = estimator.estimate(image, camera)
            predictions.append(prediction_entry(path, estimate))
            state = f"score {estimate.score:.2f}" if estimate.found else "not found"
            print(f"{path}: {state}, error ratio {estimate.error_ratio:.2f}, "
                  f"{estimate.timings.get('total', 0) * 1000:.0f} ms", file=sys.stderr)
        estimator.close()
        write_predictions(args.output, predictions)
        print(f"wrote {len(predictions)} predictions to {args.output}")

    return run(job)


if __name__ == "__main__":
    sys.exit(main())
