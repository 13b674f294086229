"""Where an image's hypotheses go and which of them the answer comes from: the funnel of the
estimator's stages, and the ranks the reported pose (and the truth) had in it, to find work
that never contributes (issue 12).

    python bench/stage_ranks.py [--latency] [--parts ...] [--conditions occl30+clutter] [--n 8] [--start 0] \
        [--align-stages]

The estimator runs as ``Estimator.estimate`` does (default parameters, its own threads), its
stages' functions wrapped to watch what passes. Per generator stage (``tetrad``, ``windows``,
``seeded``, ``small``; the climbs of the stop test before the next stage count with it,
``final`` holds the finalists' and the twin check's): the pre-filter's jobs, the matchings'
hypotheses, the poses verified on the lines (``PoseRefiner.verify``) and aligned on edge
pixels (``realign``), the starts climbed (``climb_together``).

The chosen pose's hypothesis (the pose handed to the twin check) is traced to the batch it was
verified in, and its ranks there printed (0 = best): ``job``, its (view, rotation) job's rank
by the full chamfer score in its region's pre-filter shortlist (for the seeded and small stages
its seed's rank among the search's seeds that gave a job); ``pos``, its place in the batch
handed to the refinement; ``first``, ``line``, ``end``, by the score of its first pose, of its
line end and of its end after ``realign`` (``rescued``: the aligned end replaced the line end).
``truth``: the same for the best-scoring candidate near the truth (bench/hypothesis_recall.py's
``near_truth``). Climbs: the starts climbed, how many of them the final choice's climbs use,
and how many climbs of a stop test's polished pose (fed back as a start) raised its score.
``near firsts``: first poses within 5 degrees and 5 % of the diameter of an earlier one of the
image. ``--align-stages`` also aligns every realigned hypothesis again beside the estimator and
scores it after the alignment alone: what the line rounds after it add.

``--latency``: bench/latency.py's occluded scene (sharp bracket, 2,500 views, 6 images);
otherwise bench/accuracy.py's scenes (5-degree graphs, varied look, seed 100).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import bench_steps, distractor_meshes, graph_and_model, scene  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from bench.hypothesis_recall import near_truth  # noqa: E402
from bench.latency import latency_scene  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import pose_errors  # noqa: E402
from brepose_ros.geometry import rotation_angle_deg  # noqa: E402
from brepose_ros.online import estimator as estimator_module  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.refinement import distinct_poses  # noqa: E402
from brepose_ros.online.scoring import pose_scores  # noqa: E402
from brepose_ros.online.workers import SERIAL  # noqa: E402
from brepose_ros.viewsphere import fibonacci_step  # noqa: E402

STAGES = ("tetrad", "windows", "seeded", "small", "final")
COUNTS = ("jobs", "matched", "verified", "realigned", "climbed")
RANKS = ("job", "pos", "first", "line", "end")
#: the summary's two kinds of job rank, both the ranks' ``job``
RANK_KEY = {"pre-filter": "job", "seed": "job"}


class Watch:
    """One estimator's stage functions wrapped; ``reset`` before each image."""

    def __init__(self, estimator: Estimator, align_stages: bool):
        self.e, self.align_stages = estimator, align_stages
        self.reset()
        r, h, s = estimator._refiner, estimator._hypotheses, estimator._search
        self._wrap(r, "verify", self._verify)
        self._wrap(r, "realign", self._realign)
        self._wrap(r, "climb_together", self._climb)
        self._wrap(r, "best", self._best)
        self._wrap(r, "finalists", self._finalists)
        self._wrap(r, "_climbed", self._climbed)
        self._wrap(h, "shortlist_groups", lambda f, *a, **k: self._count("jobs", f(*a, **k)))
        self._wrap(h, "match", self._match)
        self._wrap(h._views.prefilter, "shortlist", self._shortlist)
        self._wrap(s, "places", lambda f, *a, **k: (self._enter("windows"), f(*a, **k))[1])
        self._wrap(s, "best", self._search_best)
        self._module = {name: getattr(estimator_module, name) for name in ("small_part_seeds", "check_twins")}
        self._wrap(estimator_module, "small_part_seeds", lambda f, *a, **k: (self._enter("small"), f(*a, **k))[1])
        self._wrap(estimator_module, "check_twins", self._twins)

    def close(self):
        """The estimator module's functions as they were (the refiner's wrappers go with the estimator)."""
        for name, f in self._module.items():
            setattr(estimator_module, name, f)

    def reset(self):
        self.stage = "tetrad"
        self.counts = {s: dict.fromkeys(COUNTS, 0) for s in STAGES}
        self.batches: list[dict] = []
        self.origin: dict[int, tuple[int, int]] = {}  # id(hypothesis) -> (batch, place in it)
        self.job_rank: dict[int, int] = {}
        self.chamfer_rank: dict[tuple, int] = {}  # (id(region's maps), view, rotation) -> rank in its shortlist
        self.climbed: set[int] = set()  # ids of the starts climbed
        self.last_starts: list[int] = []  # of the last ``_climbed``: the final choice's
        self.settled: set[int] = set()  # ids of the stop tests' polished poses
        self.reclimbs = [0, 0]  # climbs of a polished pose, of them raised
        self.chosen = None
        self.aligned_alone: list[tuple[float, float, float, bool]] = []  # line end, aligned alone, end, rescued

    @staticmethod
    def _wrap(owner, name, hook):
        f = getattr(owner, name)
        setattr(owner, name, lambda *a, **k: hook(f, *a, **k))

    def _enter(self, stage):
        self.stage = stage

    def _count(self, key, out):
        self.counts[self.stage][key] += len(out)
        return out

    def _shortlist(self, f, maps, phis, count, *a, **k):
        """The pre-filter's shortlist (in no order), each pair's rank by its full chamfer score noted."""
        views, which = f(maps, phis, count, *a, **k)
        prefilter = self.e._hypotheses._views.prefilter
        turned = np.mod(phis[views, which].astype(np.float32), np.float32(2 * np.pi))[:, None]
        fine = prefilter._scores_of(maps, views, turned, 1, SERIAL)[:, 0]
        for rank, j in enumerate(np.argsort(fine, kind="stable")):
            self.chamfer_rank[(id(maps), int(views[j]), float(phis[views[j], which[j]]))] = rank
        return views, which

    def _match(self, f, jobs, *a, **k):
        out = self._count("matched", f(jobs, *a, **k))
        seed_rank = {}
        for region, _, _ in jobs:
            seed_rank.setdefault(id(region), len(seed_rank))
        ranks = {}
        for region, view, phi in jobs:  # a job's pre-filter rank, else (a seed's window) its seed's
            ranks.setdefault((id(region), view), self.chamfer_rank.get((id(region.distance_maps), view, phi),
                                                                      seed_rank[id(region)]))
        for hypothesis in out:
            self.job_rank[id(hypothesis)] = ranks[(id(hypothesis.region), hypothesis.view)]
        return out

    def _search_best(self, f, coarse, frame, count, *a, **k):
        if self.stage != "final" and count == self.e.params.search.seeds:
            self._enter("seeded")
        return f(coarse, frame, count, *a, **k)

    def _verify(self, f, hypotheses, *a, **k):
        out = self._count("verified", f(hypotheses, *a, **k))
        R0, t0 = self.e._refiner._first_poses(hypotheses) if hypotheses else (np.zeros((0, 3, 3)), np.zeros((0, 3)))
        self.batches.append({"stage": self.stage, "R0": R0, "t0": t0,
                             "job": np.array([self.job_rank.get(id(h), -1) for h in hypotheses]),
                             "pos": np.arange(len(out)), "first": np.array([c.first_score for c in out]),
                             "line": np.array([c.score for c in out]), "end": np.array([c.score for c in out]),
                             "R": [c.R for c in out], "t": [c.t for c in out]})
        for j, c in enumerate(out):
            self.origin[id(c.hypothesis)] = (len(self.batches) - 1, j)
        return out

    def _realign(self, f, candidates, frame, p, *a, **k):
        out = self._count("realigned", f(candidates, frame, p, *a, **k))
        for c in out:
            batch, j = self.batches[self.origin[id(c.hypothesis)][0]], self.origin[id(c.hypothesis)][1]
            batch["end"][j], batch["R"][j], batch["t"][j] = c.score, c.R, c.t
        if self.align_stages and candidates:
            refiner = self.e._refiner
            R0, t0 = refiner._first_poses([c.hypothesis for c in candidates])
            R_a, t_a = refiner.align(R0, t0, frame, p)
            alone = np.maximum(pose_scores(self.e.graph, R_a, t_a, frame, p), [c.first_score for c in candidates])
            self.aligned_alone += [(c.score, a, o.score, o.score != c.score) for c, a, o in zip(candidates, alone, out)]
        return out

    def _climb(self, f, starts, *a, **k):
        out = f(starts, *a, **k)
        if not k.get("each_alone"):  # the twin check's twins are no starts of the choice
            self.counts[self.stage]["climbed"] += len(starts)
            self.climbed.update(id(s) for s in starts)
            for start, end in zip(starts, out):
                if id(start) in self.settled and end is not None:
                    self.reclimbs[0] += 1
                    self.reclimbs[1] += end.score > start.score
        return out

    def _climbed(self, f, candidates, frame, p, *a, **k):
        out = f(candidates, frame, p, *a, **k)
        ranked = sorted(candidates, key=lambda c: -c.score)
        self.last_starts = [id(s) for s in distinct_poses(ranked, p.climb_candidates, self.e.graph.model_diameter)]
        return out

    def _best(self, f, *a, **k):
        out = f(*a, **k)
        self.settled.add(id(out))
        return out

    def _finalists(self, f, *a, **k):
        self._enter("final")
        return f(*a, **k)

    def _twins(self, f, best, *a, **k):
        self.chosen = best
        return f(best, *a, **k)

    def ranks(self, batch: int, j: int) -> dict:
        b = self.batches[batch]
        out = {"stage": b["stage"], "job": int(b["job"][j]), "pos": j, "of": len(b["pos"]),
               "rescued": bool(b["end"][j] != b["line"][j]), "scores": (b["first"][j], b["line"][j], b["end"][j])}
        out.update({key: int(np.sum(b[key] > b[key][j])) for key in ("first", "line", "end")})
        return out

    def near_firsts(self, diameter: float) -> int:
        R0 = np.concatenate([b["R0"] for b in self.batches if len(b["R0"])] or [np.zeros((0, 3, 3))])
        t0 = np.concatenate([b["t0"] for b in self.batches if len(b["t0"])] or [np.zeros((0, 3))])
        return sum(any(rotation_angle_deg(R0[j], R0[k]) < 5.0 and np.linalg.norm(t0[j] - t0[k]) < 0.05 * diameter
                       for k in range(j)) for j in range(len(R0)))


def describe(r: dict | None) -> str:
    if r is None:
        return "-"
    first, line, end = r["scores"]
    return (f"{r['stage']:7s} job {r['job']:3d} pos {r['pos']:2d}/{r['of']:2d} first {r['first']:2d} "
            f"line {r['line']:2d} end {r['end']:2d}{' rescued' if r['rescued'] else ''} "
            f"(scores {first:.2f} {line:.2f} {end:.2f})")


def watch_images(label: str, estimator: Estimator, watch: Watch, sc, images: list, model) -> list[dict]:
    rows = []
    for entry, image in zip(sc.entries, images):
        watch.reset()
        estimate = estimator.estimate(image, sc.camera)
        errors = pose_errors(estimate.R, estimate.t, entry.R, entry.t, model, estimator.graph) if estimate.found \
            else None
        chosen = None
        if watch.chosen is not None and id(watch.chosen.hypothesis) in watch.origin:
            chosen = watch.ranks(*watch.origin[id(watch.chosen.hypothesis)])
        near = [(b["end"][j], k, j) for k, b in enumerate(watch.batches) for j in range(len(b["end"]))
                if near_truth(b["R"][j], b["t"][j], entry, estimator.graph)]
        truth = watch.ranks(*max(near)[1:]) if near else None
        row = {"label": label, "image": entry.image, "found": estimate.found,
               "right": bool(errors and errors.success_sym),
               "counts": watch.counts, "chosen": chosen, "truth": truth, "climbed": len(watch.climbed),
               "used": len(set(watch.last_starts) & watch.climbed), "reclimbs": tuple(watch.reclimbs),
               "near_firsts": watch.near_firsts(estimator.graph.model_diameter),
               "hypotheses": sum(len(b["pos"]) for b in watch.batches), "aligned_alone": list(watch.aligned_alone)}
        rows.append(row)
        counts = " | ".join(f"{s} " + " ".join(str(c[k]) for k in COUNTS) for s, c in watch.counts.items())
        print(f"{label} {entry.image} found {estimate.found:d} right {row['right']:d} score {estimate.score:.2f}; "
              f"{' '.join(COUNTS)}: {counts}; climbs {row['climbed']} used {row['used']}"
              f"\n    chosen {describe(chosen)}\n    truth  {describe(truth)}", flush=True)
    return rows


def summary(rows: list[dict]) -> None:
    for label in dict.fromkeys(r["label"] for r in rows):
        of = [r for r in rows if r["label"] == label]
        right = [r for r in of if r["right"] and r["chosen"]]
        print(f"\n{label}: {len(of)} images, {len(right)} right, found but wrong "
              f"{sum(r['found'] and not r['right'] for r in of)}")
        print("  mean per image  " + "  ".join(
            f"{s}: " + "/".join(f"{np.mean([r['counts'][s][k] for r in of]):.0f}" for k in COUNTS) for s in STAGES)
            + f"   ({'/'.join(COUNTS)})")
        print(f"  hypotheses refined {np.mean([r['hypotheses'] for r in of]):.0f}, first poses within 5 deg of an "
              f"earlier {np.mean([r['near_firsts'] for r in of]):.1f}; starts climbed "
              f"{np.mean([r['climbed'] for r in of]):.1f}, used by the final choice "
              f"{np.mean([r['used'] for r in of]):.1f}; "
              f"polished poses climbed again {sum(r['reclimbs'][0] for r in of)}, raised "
              f"{sum(r['reclimbs'][1] for r in of)}")
        for who in ("chosen", "truth"):
            picked = [r[who] for r in right if r[who]]
            if picked:
                by_stage = {s: sum(p["stage"] == s for p in picked) for s in STAGES
                            if any(p["stage"] == s for p in picked)}
                prefiltered = [p for p in picked if p["stage"] in ("tetrad", "windows")]
                seeded = [p for p in picked if p["stage"] in ("seeded", "small")]
                print(f"  right images' {who}: stages {by_stage}; ranks median / max " + ", ".join(
                    f"{key} {np.median([p[RANK_KEY.get(key, key)] for p in of_key]):.0f} / "
                    f"{max(p[RANK_KEY.get(key, key)] for p in of_key)}"
                    for key, of_key in (("pre-filter", prefiltered), ("seed", seeded),
                                        *((k, picked) for k in RANKS[1:]))
                    if of_key) + f"; rescued by the alignment {sum(p['rescued'] for p in picked)}")
        alone = np.array([a for r in of for a in r["aligned_alone"]], dtype=float).reshape(-1, 4)
        if len(alone):
            line, aligned, end, rescued = alone.T
            lift = end[rescued == 1] - aligned[rescued == 1]
            print(f"  realigned {len(alone)}, rescued {int(rescued.sum())}; the line rounds after the alignment add "
                  f"(rescued) median {np.median(lift):.3f}, 90 % {np.percentile(lift, 90):.3f}, max {lift.max():.3f}; "
                  "rescued whose alignment alone scored below the line end "
                  f"{int(np.sum((aligned < line) & (rescued == 1)))}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--latency", action="store_true", help="bench/latency.py's occluded scene, 2,500 views")
    parser.add_argument("--parts", nargs="*", default=[])
    parser.add_argument("--conditions", nargs="*", default=["occl30+clutter"])
    parser.add_argument("--n", type=int, default=8)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--align-stages", action="store_true",
                        help="score each realigned hypothesis after the alignment alone too (slower)")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    rows = []
    if args.latency:
        step = bench_steps(["sharp_bracket"], cache)["sharp_bracket"]
        graph = AspectGraph.load(cached_graph_path(step, cache, fibonacci_step(2500), label="2500views"))
        estimator = Estimator(graph)
        watch = Watch(estimator, args.align_stages)
        rows += watch_images("latency occluded", estimator, watch, *latency_scene(step, cache, "occluded", 6),
                             graph_and_model(step, cache)[1])
        watch.close()
        estimator.close()
    distractors = distractor_meshes(cache) if args.parts else None
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = Estimator(graph)
        watch = Watch(estimator, args.align_stages)
        for condition in args.conditions:
            sc = scene(cache, name, step, condition, range(args.start, args.start + args.n), distractors)
            images = [cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED) for e in sc.entries]
            rows += watch_images(condition, estimator, watch, sc, images, model)
        watch.close()
        estimator.close()
    summary(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
