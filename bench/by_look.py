"""Success split by how a bench scene looks: background, motion blur, the part's size in the
image, the key light. Which looks the estimator loses is where an outside camera will hurt.

    python bench/by_look.py data/bench/results/accuracy_s17fa.json data/bench/results/accuracy_s17fb.json \\
        [--plot docs/figures/success_by_look.png]

Reads results files of ``bench/accuracy.py`` (varied look) and, for each image, the look that
the scene generator wrote into the cached scene's gt.json (``look``) and the part's mask:
its size is the diagonal of the mask's bounding box over the image's diagonal (the hidden
piece of an occluded part is not in its mask). A cell is success up to the part's exact
symmetries over the images of that look, pooled over the parts; the number of images beside
it. Looks repeat per image index across parts (the scene seed), so a level holds few
distinct looks: read a gap as a pointer to diagnose, not as a measured effect.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import scene_path  # noqa: E402
from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402

SIZE_BINS = (0.15, 0.25, 0.40)
#: Each factor: its name and the level of an image (its look, its size) it reads.
FACTORS = {
    "background": lambda look, size: look["background"],
    "motion blur": lambda look, size: "none" if look.get("motion", 0.0) == 0 else "3-9 px",
    "part size (share of the diagonal)": lambda look, size: size_level(size),
    "key light": lambda look, size: "dim (< 0.6)" if look["key_light"] < 0.6 else "bright",
}


def size_level(size: float) -> str:
    """The size's bin, named so that the bins sort by size."""
    low = max((edge for edge in (0.0, *SIZE_BINS) if edge <= size), default=0.0)
    higher = [edge for edge in SIZE_BINS if edge > size]
    return f"{low:.2f}-{higher[0]:.2f}" if higher else f"{low:.2f}+"


def mask_size(mask_path: Path) -> float:
    """The mask's bounding-box diagonal over the image's diagonal (0 for an empty mask)."""
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise FileNotFoundError(f"no mask {mask_path}")
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return 0.0
    return float(np.hypot(np.ptp(xs), np.ptp(ys)) / np.hypot(*mask.shape))


def image_looks(results: list[Path]) -> list[dict]:
    """One record per image of the results files: part, condition, right, look, size."""
    records = []
    for path in results:
        run = json.loads(path.read_text())
        if run.get("look", "varied") != "varied":
            raise SystemExit(f"{path}: only runs on the varied look carry a look per image")
        for row in run["rows"]:
            folder = scene_path(REPO / "data" / "bench", row["part"], row["condition"],
                                span=tuple(run.get("span", (0.15, 0.70))), seed=run.get("seed", 100))
            truth = {entry["image"]: entry for entry in json.loads((folder / "gt.json").read_text())}
            for image in row["images"]:
                entry = truth[image["image"]]
                right = image["found"] and image.get("success_sym", image.get("success", False))
                records.append({"part": row["part"], "condition": row["condition"], "right": bool(right),
                                "look": entry["look"],
                                "size": mask_size(folder / "masks" / Path(image["image"]).name)})
    return records


def split(records: list[dict]) -> dict[str, dict[str, dict[str, list[bool]]]]:
    """factor -> level -> condition -> the images' right flags."""
    table: dict = {name: defaultdict(lambda: defaultdict(list)) for name in FACTORS}
    for record in records:
        for name, level_of in FACTORS.items():
            table[name][level_of(record["look"], record["size"])][record["condition"]].append(record["right"])
    return table


def print_split(table, conditions: list[str]) -> None:
    for name, levels in table.items():
        print(f"\n| {name} | " + " | ".join(conditions) + " |")
        print("|---|" + "---|" * len(conditions))
        for level in sorted(levels):
            cells = [f"{np.mean(flags):.2f} ({len(flags)})" if (flags := levels[level].get(c)) else "-"
                     for c in conditions]
            print(f"| {level} | " + " | ".join(cells) + " |")


def plot_split(table, conditions: list[str], out: Path) -> None:
    figure, axes = pyplot().subplots(1, len(table), figsize=(4.2 * len(table), 3.6), sharey=True)
    width = 0.8 / len(conditions)
    for ax, (name, levels) in zip(axes, table.items()):
        order = sorted(levels)
        for k, condition in enumerate(conditions):
            rates = [np.mean(levels[level][condition]) if levels[level].get(condition) else 0.0 for level in order]
            ax.bar(np.arange(len(order)) + (k - (len(conditions) - 1) / 2) * width, rates, width, label=condition)
        ax.set_xticks(np.arange(len(order)), order, rotation=20)
        ax.set_title(name)
        ax.set_ylim(0, 1)
    axes[0].set_ylabel("success up to symmetry")
    axes[0].legend(fontsize=8)
    save_figure(figure, out, dpi=72)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, nargs="+", help="results JSON files of bench/accuracy.py")
    parser.add_argument("--plot", type=Path, help="write the split as bar charts to this PNG")
    args = parser.parse_args(argv)
    records = image_looks(args.results)
    conditions = list(dict.fromkeys(r["condition"] for r in records))
    table = split(records)
    print(f"{len(records)} images; cells: success up to symmetry (images)")
    print_split(table, conditions)
    if args.plot:
        plot_split(table, conditions, args.plot)
        print(f"\nwrote {args.plot}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
