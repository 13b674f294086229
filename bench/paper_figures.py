"""The seed paper's experiments (section 7, Fig. 7-10 and the focal length of eq. 3) redone.

    python bench/paper_figures.py [--n 10] [--figures fig7 fig8 focal fig9 fig10]
                                  [--learned config/learned.yaml] [--lonlat 16]

Every point is the mean pose error rate ``er`` (CONVENTIONS.md; an image where nothing is
found counts 0.5, a random guess) over ``--n`` random poses of the paper's two test parts,
the sharp and the rounded bracket, each measured twice: by the paper's method alone
(tetrads + Kuhn-Munkres with empty elements, the matched view as the pose, no refinement:
``Estimator.estimate(paper_only=True)``) and by the full pipeline (refined, verified,
climbed and polished). Aspect graphs on the paper's longitude/latitude grid of density
``--lonlat`` (Fig. 8 varies it). Writes docs/figures/paper_fig*.png and prints one
markdown table per figure; scenes and graphs are cached under data/bench/ (git-ignored).

* fig7: clean, centred images (paper: rounded worse than sharp).
* fig8: grid density K against error rate and time per image.
* focal: focal lengths 300-1200 px with the same projected part sizes (eq. 3: no effect).
* fig9: 0-50 % of the part hidden by a bar or pipe in front, 3 shapes of clutter behind.
* fig10: fig9's scenes with the default parameters and with ``--learned`` ones.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, evaluate_scene, mean_error_rate  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene  # noqa: E402

PARTS = ("sharp_bracket", "rounded_bracket")
FIGURES = ("fig7", "fig8", "focal", "fig9", "fig10")
METHODS = {"paper": True, "full": False}  # name -> paper_only
DENSITIES = (6, 10, 16, 24)
FOCALS = (300.0, 600.0, 1200.0)
OCCLUSIONS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
#: the paper's own curves, read off its Fig. 7-10 (error rates between about 0.1 and 0.5)
PAPER_VALUES = "error rates 0.1-0.5 (Fig. 7-10); at least 15 % lower after learning at K = 24 (section 7.1)"


@dataclass
class Point:
    mean_er: float
    success: float
    median_ms: float


class Bench:
    """Graphs, estimators, models and scenes of the two parts, each made once."""

    def __init__(self, n: int, seed: int, cache: Path):
        self.n, self.seed, self.cache = n, seed, cache
        self.steps = {part: step_file(part, cache) for part in PARTS}
        self.models = {}
        for part, step in self.steps.items():
            mesh = tessellate(load_step(step))
            self.models[part] = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        self.estimators: dict[tuple[str, int], Estimator] = {}

    def estimator(self, part: str, density: int, params: EstimatorParams) -> Estimator:
        key = (part, density)
        if key not in self.estimators:
            path = cached_graph_path(self.steps[part], self.cache, 0.0, lonlat=density)
            self.estimators[key] = Estimator(AspectGraph.load(path), params)
        estimator = self.estimators[key]
        estimator.params = params
        return estimator

    def scene(self, part: str, name: str, config: SceneConfig):
        folder = self.cache / "paper" / f"{part}_{name}_{self.n}_{self.seed}"
        if not (folder / "gt.json").exists():
            generate_scene(self.steps[part], folder, self.n, seed=self.seed, config=config)
        return load_scene(folder)

    def measure(self, part: str, name: str, config: SceneConfig, density: int, params: EstimatorParams,
                method: str) -> Point:
        results = evaluate_scene(self.scene(part, name, config), self.estimator(part, density, params),
                                 self.models[part], paper_only=METHODS[method])
        errors = [r.errors for r in results]
        times = [r.estimate.timings.get("total", 0.0) * 1000.0 for r in results]
        return Point(mean_error_rate(errors), float(np.mean([bool(e and e.success) for e in errors])),
                     float(np.median(times)))


def sweep(bench: Bench, xs, scene_of, density_of, params_of, curves) -> dict:
    """{(part, method, curve): [Point per x]}; ``scene_of(x)`` -> (name, SceneConfig)."""
    out = {}
    for part in PARTS:
        for method in METHODS:
            for curve in curves:
                out[(part, method, curve)] = [bench.measure(part, *scene_of(x), density_of(x), params_of(curve), method)
                                              for x in xs]
                print(f"  {part} {method} {curve}: " + " ".join(f"{p.mean_er:.3f}" for p in out[(part, method, curve)]),
                      file=sys.stderr)
    return out


def table(title: str, xlabel: str, xs, data: dict, with_time: bool = False) -> str:
    lines = [f"\n**{title}**\n", f"| part | method | curve | {xlabel} | mean er | success |"
             + (" median ms |" if with_time else ""), "|---|---|---|---|---|---|" + ("---|" if with_time else "")]
    for (part, method, curve), points in data.items():
        for x, p in zip(xs, points):
            lines.append(f"| {part} | {method} | {curve} | {x} | {p.mean_er:.3f} | {p.success:.2f} |"
                         + (f" {p.median_ms:.0f} |" if with_time else ""))
    return "\n".join(lines)


def plot(path: Path, title: str, xlabel: str, xs, data: dict, time_axis: bool = False) -> None:
    plt = pyplot()

    fig, axes = plt.subplots(1, 2 if time_axis else 1, figsize=(9.5 if time_axis else 5.5, 3.6), squeeze=False)
    colors = {"sharp_bracket": "tab:blue", "rounded_bracket": "tab:orange"}
    styles = {"paper": "--", "full": "-"}
    markers = {"default": "o", "learned": "s"}
    for (part, method, curve), points in data.items():
        label = f"{part.split('_')[0]} {method}" + (f" {curve}" if any(c != "default" for _, _, c in data) else "")
        kw = dict(color=colors[part], linestyle=styles[method], marker=markers[curve], markersize=4)
        axes[0, 0].plot(xs, [p.mean_er for p in points], label=label, **kw)
        if time_axis:
            axes[0, 1].plot(xs, [p.median_ms for p in points], label=label, **kw)
    axes[0, 0].set_ylabel("mean error rate er")
    axes[0, 0].set_ylim(0, 0.55)
    for ax in axes[0]:
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    if time_axis:
        axes[0, 1].set_ylabel("median time per image (ms)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=72)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=10, help="random poses per point (the paper's 10)")
    parser.add_argument("--seed", type=int, default=300)
    parser.add_argument("--lonlat", type=int, default=16, help="grid density K of every figure but fig8")
    parser.add_argument("--figures", nargs="*", default=list(FIGURES), choices=FIGURES)
    parser.add_argument("--learned", type=Path, default=REPO / "config" / "learned.yaml",
                        help="parameters after learning (fig10)")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "figures")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    bench = Bench(args.n, args.seed, cache)
    default = EstimatorParams()
    K = args.lonlat
    print(f"{args.n} images per point, seed {args.seed}, lon/lat graphs of density {K} "
          f"({K * (K - 1) + 2} views) unless said; paper: {PAPER_VALUES}")

    if "fig7" in args.figures:
        data = sweep(bench, ["clean"], lambda x: ("clean", SceneConfig()), lambda x: K, lambda c: default, ["default"])
        print(table("Fig. 7: rounded vs sharp, clean", "scene", ["clean"], data))
        plot_bars(args.out / "paper_fig7_rounded_sharp.png", data)
    if "fig8" in args.figures:
        data = sweep(bench, DENSITIES, lambda x: ("clean", SceneConfig()), lambda x: x, lambda c: default,
                     ["default"])
        print(table("Fig. 8: aspect-graph density K (K (K - 1) + 2 views)", "K", DENSITIES, data, with_time=True))
        plot(args.out / "paper_fig8_density.png", "Fig. 8: lon/lat density K, clean scenes", "density K",
             DENSITIES, data, time_axis=True)
    if "focal" in args.figures:
        data = sweep(bench, FOCALS, lambda f: (f"f{f:g}", SceneConfig(fx=f)), lambda x: K, lambda c: default,
                     ["default"])
        print(table("Focal length (eq. 3), same projected part sizes", "fx (px)", FOCALS, data))
        plot(args.out / "paper_focal.png", "focal length (eq. 3), clean, same part sizes in pixels",
             "focal length fx (px)", FOCALS, data)
    occluded = lambda o: (f"occl{o:g}_clutter3", SceneConfig(occlusion=o, clutter=3))  # noqa: E731
    if "fig9" in args.figures:
        data = sweep(bench, OCCLUSIONS, occluded, lambda x: K, lambda c: default, ["default"])
        print(table("Fig. 9: occlusion with 3 clutter shapes", "occlusion", OCCLUSIONS, data))
        plot(args.out / "paper_fig9_occlusion.png", "Fig. 9: occlusion, 3 clutter shapes behind the part",
             "share of the part hidden", OCCLUSIONS, data)
    if "fig10" in args.figures:
        learned = EstimatorParams.load(args.learned)
        data = sweep(bench, OCCLUSIONS, occluded, lambda x: K, lambda c: learned if c == "learned" else default,
                     ["default", "learned"])
        print(table(f"Fig. 10: before and after learning ({args.learned.name})", "occlusion", OCCLUSIONS, data))
        plot(args.out / "paper_fig10_learning.png", f"Fig. 10: before (o) and after (s) learning, {args.learned.name}",
             "share of the part hidden", OCCLUSIONS, data)
        for method in METHODS:
            before = np.mean([p.mean_er for (_, m, c), pts in data.items() if m == method and c == "default"
                              for p in pts])
            after = np.mean([p.mean_er for (_, m, c), pts in data.items() if m == method and c == "learned"
                             for p in pts])
            print(f"\n{method}: mean er {before:.3f} before, {after:.3f} after learning "
                  f"({100 * (after - before) / before:+.0f} %)")
    for estimator in bench.estimators.values():
        estimator.close()
    return 0


def plot_bars(path: Path, data: dict) -> None:
    """Fig. 7 as bars: one per part and method."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(5, 3.2))
    labels = [f"{part.split('_')[0]}\n{method}" for part, method, _ in data]
    values = [points[0].mean_er for points in data.values()]
    ax.bar(labels, values, color=["tab:blue" if "sharp" in lab else "tab:orange" for lab in labels])
    ax.set_ylabel("mean error rate er")
    ax.set_ylim(0, 0.55)
    ax.grid(alpha=0.3, axis="y")
    ax.set_title("Fig. 7: rounded vs sharp bracket, clean", fontsize=10)
    save_figure(fig, path, dpi=72)


if __name__ == "__main__":
    sys.exit(main())
