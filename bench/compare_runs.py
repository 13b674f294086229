"""Two accuracy-bench runs compared image by image (bench/accuracy.py's result files).

Rates over different images or different draws say little at 16 images a row; the same
image before and after says which poses a change righted and which it lost:

    python bench/compare_runs.py \
        --before data/bench/results/accuracy_s14fa.json data/bench/results/accuracy_s14fb.json \
        --after data/bench/results/accuracy_s15fa.json data/bench/results/accuracy_s15fb.json

prints, per set (tuning / leave-out) and condition, on the images both runs hold: right,
right up to the part's exact symmetries, found, and found but wrong (even up to symmetry),
before -> after; then each image whose rightness changed, and a sign test on their counts.

The estimator is sensitive: a nudge that should change nothing (Canny's threshold 5.0 ->
5.02 noise units, session 23) rights 9 and loses 20 of images 0-15, rights 25 and loses 19
of images 64-79. So read the sign test's p (two-sided, exact binomial: how often as
uneven a split of the changed images would come of a change that helps and harms alike),
judge on images nothing was chosen on (bench/accuracy.py's ``FRESH_START``), and pool ranges
before believing a difference of a few images.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scipy.stats import binomtest  # noqa: E402

from bench.accuracy import TUNING  # noqa: E402


def load_images(files: list[Path]) -> dict[tuple[str, str, str], dict]:
    """(part, condition, image) -> the image's record, over all ``files``."""
    images = {}
    for path in files:
        for row in json.loads(path.read_text())["rows"]:
            for record in row["images"]:
                images[(row["part"], row["condition"], record["image"])] = record
    return images


def counts(record: dict) -> tuple[int, int, int, int]:
    """(right, right up to symmetry, found, found but wrong up to symmetry) of one image, each
    0 or 1."""
    right, found = bool(record.get("success")), bool(record["found"])
    right_sym = bool(record.get("success_sym", right))
    return right, right_sym, found, found and not right_sym


def transitions(row: list[int]) -> str:
    """The four counts of a totals row (images, then each count before and after) as table
    cells ``before -> after``."""
    return " | ".join(f"{row[1 + 2 * i]} -> {row[2 + 2 * i]}" for i in range(4))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--before", type=Path, nargs="+", required=True, help="result files of the first run")
    parser.add_argument("--after", type=Path, nargs="+", required=True, help="result files of the second run")
    args = parser.parse_args(argv)
    before, after = load_images(args.before), load_images(args.after)
    shared = sorted(set(before) & set(after))
    if not shared:
        print("the two runs hold no image in common", file=sys.stderr)
        return 1
    totals = defaultdict(lambda: [0] * 9)
    for key in shared:
        part, condition, _ = key
        row = totals[("tune" if part in TUNING else "leave-out", condition)]
        row[0] += 1
        for i, (b, a) in enumerate(zip(counts(before[key]), counts(after[key]))):
            row[1 + 2 * i] += b
            row[2 + 2 * i] += a
    print(f"{len(shared)} images in both runs\n")
    print("| set | condition | images | right | up to symmetry | found | found but wrong |")
    print("|---|---|---|---|---|---|---|")
    for (group, condition), row in sorted(totals.items()):
        print(f"| {group} | {condition} | {row[0]} | {transitions(row)} |")
    every = [sum(row[i] for row in totals.values()) for i in range(9)]
    print(f"| all | | {every[0]} | {transitions(every)} |")
    changed = [(key, counts(after[key])[0]) for key in shared if counts(before[key])[0] != counts(after[key])[0]]
    for label, now_right in (("righted", True), ("lost", False)):
        names = [f"{part} {condition} {Path(image).stem}" for (part, condition, image), r in changed if r == now_right]
        print(f"\n{label} ({len(names)}): " + (", ".join(names) if names else "none"))
    righted = sum(r for _, r in changed)
    if changed:
        p_value = binomtest(righted, len(changed), 0.5).pvalue
        print(f"\nsign test: {righted} righted, {len(changed) - righted} lost, two-sided p = {p_value:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
