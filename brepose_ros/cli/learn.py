"""brepose-learn: tune the estimator's thresholds on the training shapes (seed paper, section 6).

Renders training scenes of the built-in training shapes (cube, box, cylinder, an L block and
a wedge) in the accuracy bench's conditions and look, compiles their aspect graphs, searches
the parameters of ``evaluation.learning.SEARCH_SPACE`` with optuna (the defaults first) for
the lowest error rate of the paper's method, then re-scores the best few trials and the
defaults on held-out images of the same shapes: the parameter file written changes the
defaults only when a trial beats them there too. Every trial is logged to a CSV beside it.
Needs the [compile] and [learn] extras.
"""
from __future__ import annotations

import sys
from pathlib import Path

from .common import ArgumentParser, non_negative_int, positive_float, positive_int, run

EXAMPLE = """example:
  brepose-learn -o config/learned.yaml --trials 60 --minutes 30      (writes config/learned.trials.csv too)
  brepose-estimate --params config/learned.yaml ...       (CLIs)
  estimator --params-file config/node.yaml --params-file config/learned.yaml   (the ROS node)"""


def parse_args(argv=None):
    parser = ArgumentParser(prog="brepose-learn", description=__doc__.splitlines()[0], epilog=EXAMPLE)
    parser.add_argument("-o", "--out", type=Path, default=Path("config/learned.yaml"), help="parameter file to write")
    parser.add_argument("--trials", type=non_negative_int, default=60, help="parameter sets tried after the defaults")
    parser.add_argument("--minutes", type=positive_float, default=30.0,
                        help="the whole run's time (scenes, graphs and the held-out re-scoring included)")
    parser.add_argument("--n", type=positive_int, default=16, help="training images per shape and condition")
    parser.add_argument("--held-out-n", type=positive_int, default=24,
                        help="held-out images per shape and condition (another seed)")
    parser.add_argument("--finalists", type=positive_int, default=3,
                        help="best trials re-scored on the held-out images")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the scenes and of the sampler")
    parser.add_argument("--step-deg", type=positive_float, default=10.0, help="view spacing of the training graphs")
    parser.add_argument("--latency-factor", type=positive_float, default=1.5,
                        help="latency budget: this many times the defaults' median time per image")
    parser.add_argument("--cache", type=Path, default=Path("data/learn"),
                        help="folder for the training scenes and graphs (reused when present)")
    return parser.parse_args(argv)


def trials_path(out: Path) -> Path:
    """The trial log beside the parameter file: learned.yaml -> learned.trials.csv."""
    return out.with_suffix(".trials.csv")


def main(argv=None) -> int:
    args = parse_args(argv)

    def job():
        import time

        from tqdm import tqdm

        try:
            import optuna  # noqa: F401
        except ImportError:
            raise ValueError("brepose-learn needs optuna: pip install 'brepose_ros[learn]'") from None

        from ..evaluation.learning import (HELD_OUT_SEED_OFFSET, TRAINING_CONDITIONS, TRAINING_SHAPES, learn,
                                           training_parts, write_learned, write_trials)

        start = time.perf_counter()
        print(f"preparing {len(TRAINING_SHAPES)} training shapes x {len(TRAINING_CONDITIONS)} conditions x "
              f"{args.n} + {args.held_out_n} held-out images in {args.cache}", file=sys.stderr)
        train, held_out = training_parts(args.cache, n=args.n, seed=args.seed, step_deg=args.step_deg,
                                         held_out_n=args.held_out_n)
        print(f"prepared in {(time.perf_counter() - start) / 60:.1f} min; the defaults on the held-out and the "
              f"training images first", file=sys.stderr)
        left = args.minutes * 60.0 - (time.perf_counter() - start)
        log = trials_path(args.out)
        with tqdm(total=args.trials + 1, desc="trials", unit="trial") as bar:
            def on_record(record: dict, records: list[dict]):
                write_trials(log, records)
                if record["held_out_loss"] is not None and record["trial"] > 0:
                    bar.write(f"held-out: trial {record['trial']} loss {record['held_out_loss']:.4f}")
                    return
                held = f", held-out {record['held_out_loss']:.4f}" if record["held_out_loss"] is not None else ""
                bar.write(f"trial {record['trial']}: loss {record['loss']:.4f} (er {record['error_rate']:.4f} "
                          f"+- {record['standard_error']:.4f}, {record['median_ms']:.0f} ms{held}) "
                          f"{record['seconds']:.0f} s")
                bar.update(1)
                bar.set_postfix(best=f"{min(r['loss'] for r in records):.4f}")

            result = learn(train, held_out, args.trials, left, args.latency_factor, args.seed, args.finalists,
                           on_record)
        for part in train:
            part.estimator.close()
        provenance = {"shapes": ", ".join(TRAINING_SHAPES),
                      "conditions": "; ".join(f"{k} {v}" for k, v in TRAINING_CONDITIONS.items()),
                      "images": f"{args.n} per shape and condition, seed {args.seed}; held out {args.held_out_n}, "
                                f"seed {args.seed + HELD_OUT_SEED_OFFSET}; graphs at {args.step_deg:g} deg",
                      "trials": f"{log.name} (every trial's parameters and losses)",
                      "command": "brepose-learn " + " ".join(sys.argv[1:] if argv is None else argv)}
        write_learned(args.out, result, provenance)
        print(f"{result.verdict.reason}\n{len(result.trials) - 1} trials in "
              f"{(time.perf_counter() - start) / 60:.1f} min; wrote {args.out} and {log}")

    return run(job)


if __name__ == "__main__":
    sys.exit(main())
