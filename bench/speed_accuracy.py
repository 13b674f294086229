"""Right poses against time per image, one point per run of bench/accuracy.py: the operating
points a cell chooses between (``search.time_budget_ms``, ``search.generators``).

    python bench/speed_accuracy.py default=data/bench/results/accuracy_budget26_0.json \\
        "budget 250 ms=data/bench/results/accuracy_budget26_250.json" ... [--out docs/figures/F.png]

Each argument is a results JSON, optionally prefixed ``LABEL=`` (files of one label are
merged, as bench/plot_accuracy.py does). The runs should hold the same images and have
been run one at a time on an otherwise idle machine: the times are the estimator's own
(``Estimate.timings["total"]``), which another process beside it slows. Prints per run the
images right up to exact symmetries (found and within CONVENTIONS.md's bounds) by condition,
the found but wrong, and the median and 90th percentile ms per image; the plot puts the
right share against the median time, the 90th percentile as the bar's right end.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.compare_runs import counts  # noqa: E402
from bench.plot_accuracy import load_runs  # noqa: E402
from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402


def operating_point(rows: list[dict]) -> dict:
    """Right (found, success up to symmetry) per condition and overall, found but wrong, and
    the ms per image of all the run's images."""
    images = [(row["condition"], image) for row in rows for image in row["images"]]
    tallies = [counts(i) for _, i in images]  # (right, right up to symmetry, found, found but wrong)
    right = [bool(sym and found) for _, sym, found, _ in tallies]
    conditions = dict.fromkeys(c for c, _ in images)
    ms = np.array([i["ms"] for _, i in images])
    return {"images": len(images), "right": sum(right),
            "by_condition": {c: sum(r for (cc, _), r in zip(images, right) if cc == c) for c in conditions},
            "per_condition": {c: sum(cc == c for cc, _ in images) for c in conditions},
            "wrong": sum(wrong for *_, wrong in tallies),
            "median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", help="[LABEL=]results.json of bench/accuracy.py")
    parser.add_argument("--out", type=Path, help="PNG to write (default: print the table only)")
    args = parser.parse_args(argv)
    points = {label: operating_point(rows) for label, rows in load_runs(args.results).items()}
    conditions = list(next(iter(points.values()))["per_condition"])
    print("| run | images | right | " + " | ".join(f"right, {c}" for c in conditions)
          + " | found but wrong | ms/image (median) | 90 % |")
    print("|" + "---|" * (6 + len(conditions)))
    for label, p in points.items():
        print(f"| {label} | {p['images']} | {p['right']} | "
              + " | ".join(f"{p['by_condition'][c]} of {p['per_condition'][c]}" for c in conditions)
              + f" | {p['wrong']} | {p['median_ms']:.0f} | {p['p90_ms']:.0f} |")
    if args.out:
        plt = pyplot()
        fig, ax = plt.subplots(figsize=(9, 4.5))
        for (label, p), marker in zip(points.items(), "osD^v<>ph*"):
            share = p["right"] / p["images"]
            ax.errorbar([p["median_ms"]], [share], xerr=[[0.0], [p["p90_ms"] - p["median_ms"]]], fmt=marker,
                        capsize=3, label=label)
        ax.set_xlabel("ms per image (median; bar to the 90th percentile)")
        ax.set_ylabel("right up to symmetry, share of images")
        ax.set_xlim(left=0)
        ax.grid(alpha=0.3)
        ax.legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=8)
        save_figure(fig, args.out, dpi=90)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
