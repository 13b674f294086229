"""Success against occlusion (0-50 %, with clutter) per part set, one line per results file:
the seed paper's Fig. 9 (error rate against occlusion) as this project measures it.

    python bench/plot_accuracy.py data/bench/results/accuracy_default.json
    python bench/plot_accuracy.py tetrad=data/bench/results/accuracy_tetrad.json \\
        search=data/bench/results/accuracy_search.json both=...json [--metric success_sym|add_s] [--out FIG.png]

Each argument is a results JSON of ``bench/accuracy.py`` (or any file of the same layout,
e.g. a peer's), optionally prefixed ``LABEL=``; without a label the file's own is used, and
files of one label are merged (a run split by part).
Occlusion 0 is the ``clutter`` condition, 10-50 % the ``occlNN+clutter`` ones; rates are
pooled over each set's parts. The ``clean`` rate is drawn as a marker left of the axis' zero.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402

METRICS = {"success": ("success", "success (rot < 5 deg, t < 5 % d)"),
           "success_sym": ("success_sym", "success up to exact symmetry"),
           "add_s": ("add_s", "ADD-S < 0.1 d")}
SETS = ("tune", "leave-out")


def rate(images: list[dict], metric: str) -> float:
    if metric in ("success", "success_sym"):
        hits = sum(bool(i.get(metric, False)) for i in images)
    else:
        hits = sum(i.get("add_s", 1.0) < 0.1 for i in images)
    return hits / len(images) if images else float("nan")


def curve(rows: list[dict], part_set: str, metric: str) -> tuple[list[float], list[float], float]:
    """(occlusion %, rate) with clutter, and the clean rate, pooled over the set's parts."""
    chosen = [r for r in rows if r["set"] == part_set]
    xs, ys = [], []
    for row_occlusion in sorted({r["occlusion"] for r in chosen if r["clutter"] > 0}):
        images = [i for r in chosen if r["clutter"] > 0 and r["occlusion"] == row_occlusion for i in r["images"]]
        xs.append(100.0 * row_occlusion)
        ys.append(rate(images, metric))
    clean = [i for r in chosen if r["condition"] == "clean" for i in r["images"]]
    return xs, ys, rate(clean, metric)


def labelled(argument: str) -> tuple[str, Path]:
    """``[LABEL=]results.json`` as (label, empty without one; path)."""
    label, _, path = argument.rpartition("=")
    return label, Path(path)


def load_runs(arguments: list[str]) -> dict[str, list[dict]]:
    """{label: rows} of ``[LABEL=]results.json`` arguments, the rows of one label's files
    merged (a run split by part); without a label, the file's own."""
    runs: dict[str, list[dict]] = {}
    for item in arguments:
        label, path = labelled(item)
        data = json.loads(path.read_text())
        label = label or data.get("label", Path(path).stem)
        runs[label] = runs.get(label, []) + data["rows"]
    return runs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", help="[LABEL=]results.json of bench/accuracy.py")
    parser.add_argument("--metric", choices=list(METRICS), default="success")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "figures" / "accuracy_vs_occlusion.png")
    args = parser.parse_args(argv)
    plt = pyplot()
    runs = list(load_runs(args.results).items())
    key, axis_label = METRICS[args.metric]
    fig, axes = plt.subplots(1, len(SETS), figsize=(5.2 * len(SETS), 4.0), sharey=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, part_set in zip(axes, SETS):
        for k, ((label, rows), colour) in enumerate(zip(runs, colours)):
            xs, ys, clean = curve(rows, part_set, key)
            if not xs:
                continue
            chosen = [r for r in rows if r["set"] == part_set and r["condition"] == "clean"]
            n_parts = len({r["part"] for r in chosen})
            per_part = sum(len(r["images"]) for r in chosen) // max(n_parts, 1)
            ax.plot(xs, ys, "o-", color=colour, label=f"{label} ({n_parts} parts, {per_part} images each)")
            # the clean markers side by side, so that equal rates do not hide one another
            ax.plot([-5 + 1.2 * (k - (len(runs) - 1) / 2)], [clean], "s", color=colour, markerfacecolor="none")
        ax.set_title(f"{part_set} parts")
        ax.set_xlabel("occlusion with clutter (%)   [square: clean]")
        ax.set_xticks([-5, 0, 10, 20, 30, 40, 50], ["clean", "0", "10", "20", "30", "40", "50"])
        ax.set_xlim(-8, 53)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[0].set_ylabel(axis_label)
    first = json.loads(labelled(args.results[0])[1].read_text())  # its look and commit name the figure
    fig.suptitle(f"bench/accuracy.py, {first.get('look', '?')} look, commit {first.get('commit', '?')}", fontsize=9)
    save_figure(fig, args.out, dpi=90)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
