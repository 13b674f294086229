"""brepose-learn: tune the estimator's thresholds on the training shapes (seed paper, section 6).

Renders training scenes of the built-in cube, box and cylinder (clean, and 25 % occluded
among 3 clutter shapes under random lights), compiles their aspect graphs, searches the parameters of
``evaluation.learning.SEARCH_SPACE`` with optuna (the defaults first) and writes the best
as a parameter file with its provenance. Needs the [compile] and [learn] extras.
"""
from __future__ import annotations

import sys
from pathlib import Path

from .common import ArgumentParser, non_negative_int, positive_float, positive_int, run

EXAMPLE = """example:
  brepose-learn -o config/learned.yaml --trials 60 --minutes 25
  brepose-estimate --params config/learned.yaml ...       (CLIs)
  estimator --params-file config/node.yaml --params-file config/learned.yaml   (the ROS node)"""


def parse_args(argv=None):
    parser = ArgumentParser(prog="brepose-learn", description=__doc__.splitlines()[0], epilog=EXAMPLE)
    parser.add_argument("-o", "--out", type=Path, default=Path("config/learned.yaml"), help="parameter file to write")
    parser.add_argument("--trials", type=non_negative_int, default=60, help="parameter sets tried after the defaults")
    parser.add_argument("--minutes", type=positive_float, default=25.0,
                        help="stop searching after this long (scene and graph preparation included)")
    parser.add_argument("--n", type=positive_int, default=4, help="images per training shape and condition")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the scenes and of the sampler")
    parser.add_argument("--step-deg", type=positive_float, default=10.0, help="view spacing of the training graphs")
    parser.add_argument("--latency-factor", type=positive_float, default=1.5,
                        help="latency budget: this many times the defaults' median time per image")
    parser.add_argument("--cache", type=Path, default=Path("data/learn"),
                        help="folder for the training scenes and graphs (reused when present)")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)

    def job():
        import time

        from tqdm import tqdm

        try:
            import optuna  # noqa: F401
        except ImportError:
            raise ValueError("brepose-learn needs optuna: pip install 'brepose_ros[learn]'") from None

        from ..evaluation.learning import TRAINING_CONDITIONS, TRAINING_SHAPES, learn, training_parts, write_learned

        start = time.perf_counter()
        print(f"preparing {len(TRAINING_SHAPES)} training shapes x {len(TRAINING_CONDITIONS)} conditions x "
              f"{args.n} images in {args.cache}", file=sys.stderr)
        parts = training_parts(args.cache, n=args.n, seed=args.seed, step_deg=args.step_deg)
        left = args.minutes * 60.0 - (time.perf_counter() - start)
        with tqdm(total=args.trials, desc="trials", unit="trial") as bar:
            def on_trial(number: int, loss: float, best: float, score):
                bar.write(f"trial {number}: loss {loss:.3f} {score.to_dict()}")
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.3f}", best=f"{best:.3f}")

            result = learn(parts, args.trials, left, args.latency_factor, args.seed, on_trial)
        for part in parts:
            part.estimator.close()
        provenance = {"shapes": ", ".join(TRAINING_SHAPES),
                      "conditions": "; ".join(f"{k} {v or ''}".strip() for k, v in TRAINING_CONDITIONS.items()),
                      "images": f"{args.n} per shape and condition, seed {args.seed}, graphs at {args.step_deg:g} deg",
                      "command": "brepose-learn " + " ".join(sys.argv[1:] if argv is None else argv)}
        write_learned(args.out, result, provenance)
        print(f"defaults: {result.default.to_dict()}\nlearned:  {result.best.to_dict()}\n"
              f"{result.trials} trials in {(time.perf_counter() - start) / 60:.1f} min; wrote {args.out}")

    return run(job)


if __name__ == "__main__":
    sys.exit(main())
