"""Every tunable number of the online pipeline, typed and documented in one place.

Each field carries its documentation in ``metadata["doc"]``; the ROS node declares one
parameter per field from it (``matching.empty_coefficient`` etc.) and ``config/estimator.yaml``
holds the same defaults for users to copy. Groups follow the pipeline stages.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

DETECTORS = ("hough", "lsd")


def doc(text: str, default: Any, low: float | None = None, high: float | None = None) -> Any:
    """A dataclass field with its default, its documentation in ``metadata["doc"]`` and, for
    numbers, its closed range ``[low, high]`` in ``metadata["range"]`` (the ROS node puts it
    in the parameter's descriptor; ``check_ranges`` refuses values outside it)."""
    metadata = {"doc": text}
    if low is not None:
        metadata["range"] = (low, high)
    return field(default=default, metadata=metadata)


def check_ranges(instance) -> None:
    """ValueError naming the first field of a params dataclass outside its range (or NaN)."""
    for f in dataclasses.fields(instance):
        if "range" not in f.metadata:
            continue
        value, (low, high) = getattr(instance, f.name), f.metadata["range"]
        if not low <= value <= high:  # also refuses NaN
            raise ValueError(f"{f.name} must be in [{low:g}, {high:g}], got {value}")


class Ranged:
    """Mix-in of the params groups: every value is checked against its range when made."""

    def __post_init__(self):
        check_ranges(self)


@dataclass(frozen=True)
class EdgeParams(Ranged):
    """Every threshold of the image edge stage; lengths in pixels unless named ``*_fraction``."""

    detector: str = doc("'hough' (Canny + HoughLinesP, the paper's method) or 'lsd' (OpenCV LSD)", "hough")
    blur_size: int = doc("odd Gaussian kernel size before edge detection; 1 disables the blur", 5, 1, 31)
    blur_sigma: float = doc("Gaussian sigma, pixels; 0 derives it from blur_size", 0.0, 0.0, 20.0)
    colour: bool = doc(
        "colour images: Canny at each pixel on the luminance or one of two opponent-colour planes (red - green, "
        "yellow - blue), whichever stands out most above its own noise threshold: the grey image's edges plus the "
        "boundaries of like brightness and another hue (docs/results/real_lmo.md); false: the grey image's only",
        True)
    canny_noise_factor: float = doc(
        "Canny high threshold in units of the gradient noise level (median gradient / 1.18)", 5.0, 0.1, 100.0)
    canny_low_ratio: float = doc("Canny low threshold as a share of the high one", 0.4, 0.01, 1.0)
    canny_min_high: float = doc(
        "floor of the Canny high threshold (Sobel magnitude of a 0..255 image) for noise-free images", 6.0, 0.1, 1000.0)
    hough_rho: float = doc("HoughLinesP distance resolution, pixels", 1.0, 0.5, 10.0)
    hough_theta_deg: float = doc("HoughLinesP angle resolution, degrees", 1.0, 0.1, 10.0)
    hough_vote_ratio: float = doc(
        "HoughLinesP accumulator threshold as a share of the minimum line length", 0.5, 0.01, 10.0)
    raw_min_length_fraction: float = doc(
        "shortest raw segment before merging (HoughLinesP minLineLength; shorter LSD pieces are dropped), "
        "share of the image diagonal", 0.0075, 0.0, 1.0)
    refine_raw_min_length_fraction: float = doc(
        "raw_min_length_fraction of the segments the pose refinement pairs with (a Hough pass of their own): "
        "the short pieces of curved outlines that help small parts' search pull near poses' depth off "
        "(docs/results/real_lmo.md)", 0.015, 0.0, 1.0)
    hough_max_gap: float = doc("largest gap HoughLinesP bridges inside one segment, pixels", 3.0, 0.0, 100.0)
    merge_angle_deg: float = doc("pieces of one edge differ in direction by at most this, degrees", 2.0, 0.1, 45.0)
    merge_distance: float = doc(
        "both end points of a piece lie this close to the edge's fitted line, pixels", 2.0, 0.0, 50.0)
    merge_gap: float = doc("largest gap along the line between pieces of one edge, pixels", 15.0, 0.0, 500.0)
    refine: bool = doc("refit each merged Hough segment to the Canny pixels along it and extend it over them", True)
    min_length_fraction: float = doc(
        "merged segments shorter than this share of the image diagonal are dropped; 0.015 (12 px at 640x480) keeps "
        "the edges of a part 50-150 px across, half of whose edge length lies in shorter edges "
        "(docs/results/real_lmo.md)", 0.015, 0.0, 1.0)
    max_segments: int = doc("at most this many merged segments are kept, longest first", 200, 1, 2000)
    background_line_fraction: float = doc(
        "an image line whose collinear segments reach across at least this share of the image diagonal (and add "
        "up to half of that), in a row of background_pattern_lines such lines, is the background's pattern (a "
        "table's seams, tiles, slats, a perforated plate's rows), not a part's edges: its edge pixels are dropped "
        "before the segments and the score (docs/results/backgrounds.md); 0: no line is", 0.4, 0.0, 4.0)
    background_pattern_lines: int = doc(
        "background_line_fraction: this many such lines at least, parallel within merge_angle_deg, make a "
        "background's pattern (the bench's ruled tables show 20-80; a long rod in front shows up to 6, with its "
        "shading's edges, and a grained surface 1-3)", 8, 1, 1000)
    colour_regions: bool = doc(
        "parts whose model has colour (a scanned mesh with vertex colours), in colour images: only the edge pixels "
        "in the regions of the part's own chromaticity count (online/colour_regions.py), so that the search and "
        "the score do not look at the rest of the scene; parts without colour (STEP) and grey images always use "
        "the whole image (docs/results/real_lmo.md)", True)
    colour_region_threshold: float = doc(
        "colour_regions: a pixel belongs to the part's regions when its colour's share of the model over its share "
        "of the image (a histogram ratio, at most 1) reaches this", 0.5, 0.0, 1.0)
    colour_places: int = doc(
        "colour_regions: where the regions split into places (the part, its shadow, things of like colour), the "
        "estimate is made again within each of this many alone, those holding the most of the part's colour "
        "first (none where one holds nearly all the regions: a grey part's desk), and a pose found there replaces the "
        "whole regions' one where it scores more on the whole regions' edges: among several places the whole "
        "regions' search often seeds none at the part's (LM-O photos: 6.3 -> 9.5 % ADD(-S) at 1.6x the time, "
        "docs/results/real_lmo.md); 0: the whole regions only", 3, 0, 16)

    def __post_init__(self):
        if self.detector not in DETECTORS:
            raise ValueError(f"detector must be one of {DETECTORS}, got {self.detector!r}")
        super().__post_init__()
        if self.blur_size % 2 == 0:
            raise ValueError(f"blur_size must be a positive odd integer, got {self.blur_size}")


@dataclass(frozen=True)
class MatchParams(Ranged):
    """Tetrad metric space and bipartite matching (seed paper sections 3 and 6)."""

    weight_length: float = doc("weight of the length difference in the tetrad distance", 1.0, 0.0, 100.0)
    weight_midpoint: float = doc(
        "weight of the midpoint difference (length and angle of the midpoint)", 1.0, 0.0, 100.0)
    weight_orientation: float = doc(
        "weight of the orientation difference (angle of the perpendicular), radians", 0.5, 0.0, 100.0)
    weight_perpendicular: float = doc(
        "weight of the perpendicular foot-point difference (length and angle of the perpendicular)", 0.5, 0.0, 100.0)
    empty_coefficient: float = doc(
        "distance of an empty element, as a share of the largest pair distance; pairs farther than twice this"
        " are left unmatched", 0.25, 0.001, 10.0)
    nearest_threshold: float = doc(
        "pairs closer than this share of the empty distance form the nearest group", 0.5, 0.0, 1.0)
    shortlist_size: int = doc(
        "(view, rotation) pairs per region kept by the chamfer pre-filter for Kuhn-Munkres", 48, 1, 256)
    rotation_candidates: int = doc(
        "peaks of the orientation correlation tried per view, each also turned by 180 degrees", 2, 1, 16)
    coverage_tolerance: float = doc(
        "distance (normalised units) within which aligned edges cover each other when ranking views", 0.04, 0.001, 1.0)
    max_model_segments: int = doc("longest view segments used in matching", 60, 4, 200)
    max_image_segments: int = doc("longest image segments used in matching per region", 90, 4, 300)
    max_regions: int = doc("candidate image regions (whole image, edge clusters) matched per image", 6, 1, 32)
    cluster_gap_fraction: float = doc(
        "segments whose end points lie closer than this share of the image diagonal chain into one cluster "
        "(a candidate region); as long as the shortest segment kept (edges.min_length_fraction), so that the "
        "edges of one part meeting at its corners chain, while objects apart by more stay apart", 0.015, 0.0, 0.5)
    hypotheses: int = doc(
        "best-covered (view, rotation) hypotheses per region turned into poses and verified", 6, 1, 64)
    workers: int = doc(
        "worker threads sharing one image's work (the pre-filter's views, the matching jobs, the poses refined "
        "and scored); 0 = one per CPU core. On 2 free cores 2 threads measured 1.18x clean and 1.46x occluded "
        "with the same poses; with a core busy with other work 0.9-1.0x: set 1 where the node shares its "
        "cores (bench/latency.py, docs/results/latency.md)", 0, 0, 16)


@dataclass(frozen=True)
class PoseParams(Ranged):
    """Metric pose, refinement and the found / not-found decision."""

    # refine_iterations stops at 6: the estimator's refinement schedule has 6 rounds
    refine_iterations: int = doc(
        "re-match and refine rounds of every hypothesis; 0 keeps the first pose from the view", 6, 0, 6)
    climb_candidates: int = doc(
        "best-scoring distinct refined hypotheses that go on to the search over neighbouring views; 4 rather "
        "than 2: under occlusion and clutter the start that climbs to the truth was not among the best two in 3 "
        "of 72 tuning images, none lost, about 5 % more time (docs/results/occlusion.md)", 4, 1, 16)
    view_search_steps: int = doc(
        "steps of the hill-climb over neighbouring aspect-graph views; 0 turns it off", 4, 0, 50)
    inlier_pixels: float = doc(
        "distance of a projected model edge to an image edge still counted as found, pixels", 2.0, 0.1, 50.0)
    outline_pixels: float = doc(
        "inlier_pixels of the outlines of curved faces (soft silhouettes, whose image edge lies off them where the "
        "face turns dark), pixels; 2, as the sharp edges: 3 cut LM-O's renders from 19 to 8 % ADD(-S) with the "
        "render bench level (docs/results/real_lmo.md)", 2.0, 0.1, 50.0)
    polish_fine_pixels: float = doc(
        "radius of the polish's last two pairings on edge pixels, after its three at inlier_pixels, pixels: at 2 px "
        "the polish leaves a small, blurred part's depth too far (from the truth 40 of 480 bench images leave the "
        "bounds, 29 on the small or blurred images 7 and 14); with them the bench's right 213 -> 216 of 480, wrong "
        "reported 72 -> 71 (bench/near_misses.py, docs/results/refinement.md); 0 turns them off", 1.0, 0.0, 50.0)
    seen_pixels: float = doc(
        "a cell of the score's explained share also counts as seen where half its model length lies this near like "
        "edges beyond chance, pixels: a pose turned a few degrees off the part's features has their edges beside "
        "its own, an occluder hides them (bench: wrong poses reported 104 -> 91 of 480 images, right 191 -> 193, "
        "docs/results/refinement.md). It costs another set of maps per image, about 2 ms of CPU on a clean image since "
        "the maps cover the edge pixels' box only (docs/results/latency.md); at most inlier_pixels turns it off, the "
        "score as before", 6.0, 0.0, 20.0)
    min_size_pixels: float = doc(
        "smallest diagonal of the projected part, pixels; smaller poses score 0", 40.0, 0.0, 10000.0)
    min_margin_pixels: float = doc(
        "floor of the margin around a pose's projected outline inside which the score counts edge pixels the pose "
        "does not explain, pixels: stops a small pose that fits one inner feature of the part (a hole) from "
        "outscoring the whole part", 40.0, 0.0, 1000.0)
    min_score: float = doc(
        "floor of the found rule: a pose with a lower score is reported as not found, whatever its confidence "
        "(0.45: on 192 images per part and condition, at pose.min_confidence 0.08 then, no lower floor finds "
        "another right pose, and 0.55 lost 12 right tuning and 30 right leave-out poses; docs/results/confidence.md)",
        0.45, 0.0, 1.0)
    min_confidence: float = doc(
        "a pose whose confidence (the calibrated probability that it is right, online/confidence.py, weighing the "
        "edges' evidence and the shading fit) is lower is reported as not found. The default was chosen by "
        "bench/confidence.py on the tuning parts to find at least as many right poses as score >= 0.6 at no lower "
        "precision (docs/results/confidence.md). 0.55, the bench's trusted rule, reports fewer than half the "
        "right poses: on the accuracy bench's fresh images 64-95 (960, the part always in view) 250 of 274 "
        "right up to symmetry (91 %; 211 of 232 before the confidence weighed the shading fit), on 128 images "
        "per part and condition of the confidence's bench (64-191, session 22's fit) 340 of 387 (88 %) and 381 "
        "of 387 within ADD(-S) 0.1 d: the wrong ones are near misses (a depth 5-10 % of the diameter off, a "
        "turn of 5-10 degrees) and half turns of near-symmetric parts. 0.8: 46 of 48 on the fresh 960",
        0.09, 0.0, 1.0)
    min_shading_fit: float = doc(
        "a pose whose shading fit is lower is reported as not found: how much of the image's grey level over the "
        "part's silhouette the part's surface normals at the pose explain under some light (online/appearance.py, "
        "about 3 ms an image); it needs an aspect graph holding the part's surface (compiled since session 27: "
        "recompile an older one). 0: no floor (the confidence weighs the fit either way). On 960 fresh bench "
        "images (64-95), on top of the confidence that weighs it: with pose.min_confidence 0.55, 0.7 reports "
        "246 of 261 right up to symmetry (94 %) against 250 of 274 (91 %); at the default found rule 0.6 drops "
        "30 of 186 wrong poses and 6 of 413 right ones (session 28; 0.7 was chosen on images 64-79 in session "
        "27). A silhouette of one evenly lit face has little to explain and fits low "
        "at the truth too (docs/results/verification.md)", 0.0, 0.0, 1.0)
    prior: float = doc(
        "how often the part is in view, as a share of the images (1: always); the confidence is moved by Bayes' "
        "rule from the mix it was fitted at (half the images, brepose_ros/confidence.yaml) to this, so that it is "
        "the probability that the pose is right where the part is this often in view", 0.5, 0.0, 1.0)
    confidence_file: str = doc(
        "calibration file of the confidence (bench/confidence.py --fit writes one); empty: the shipped "
        "brepose_ros/confidence.yaml", "")
    warn_error_ratio: float = doc("diagnostics turn WARN above this error ratio", 0.5, 0.0, 1.0)
    twin_check: bool = doc(
        "compare the final pose with its twins under the part's near symmetries (stored in the aspect graph) on "
        "the edges that tell them apart, and keep the one the image confirms", True)
    larger_check: bool = doc(
        "when the final pose scores below search.enough_score, search again about its place for larger poses "
        "(``online/larger.py``: a shrunken, turned copy of the part lying on its own edges) and keep one that "
        "scores more, or nearly as much with more evidence against chance. On 1,440 fresh bench images the check "
        "by the score alone righted 13 and lost 2 (right 519 -> 530), the evidence another 16 and 1 (530 -> 545, "
        "found but wrong 283 -> 265; its rule chosen on images 64-79, 12 righted and 2 lost on 80-127); LM-O "
        "unchanged; about 1.3x the time of an image that scores below search.enough_score; false where that "
        "time matters more (docs/results/depth.md)", True)
    twin_margin: float = doc(
        "a pose whose evidence over its best twin (difference of the shares of their distinguishing edges the "
        "image confirms) is below this is reported ambiguous", 0.2, 0.0, 1.0)
    min_distance: float = doc(
        "the nearest the part's model centre can be to the camera, metres; 0: unknown. With pose.max_distance, "
        "a known working distance: the template search tries only the part's sizes between the two, and a pose "
        "outside them is reported as not found (docs/results/occlusion.md)", 0.0, 0.0, 1000.0)
    max_distance: float = doc(
        "the farthest the part's model centre can be from the camera, metres; 0: unknown (see pose.min_distance)",
        0.0, 0.0, 1000.0)

    def __post_init__(self):
        super().__post_init__()
        if 0 < self.max_distance < self.min_distance:
            raise ValueError(f"min_distance ({self.min_distance:g} m) must not exceed max_distance "
                             f"({self.max_distance:g} m)")

    @property
    def distances(self) -> tuple[float, float]:
        """The working range (min_distance, max_distance), metres; 0: that end unknown."""
        return self.min_distance, self.max_distance

    def within_distance(self, distance: float) -> bool:
        """Whether a pose whose model centre lies ``distance`` metres away is in the working range."""
        return distance >= self.min_distance and (self.max_distance == 0 or distance <= self.max_distance)


#: the hypothesis generators (``search.generators`` joins them with '+', run in that order)
GENERATORS = ("tetrad", "search", "seeded", "windows", "small")


@dataclass(frozen=True)
class SearchParams(Ranged):
    """The hypothesis generators: the paper's region-normalised tetrads and the template
    search over gradient directions (``online/search.py``)."""

    generators: str = doc(
        "hypothesis generators, joined by '+' and run in that order: 'tetrad' (regions + bipartite matching), "
        "'search' (templates slid over the image, no region normalised), 'seeded' (the search's best templates "
        "as seeds of the bipartite matching, each normalised in its own frame), 'windows' (the tetrad generator on "
        "windows about the search's best places instead of the whole image and clusters), 'small' (templates below "
        "min_size_fraction's size slid only over patches of edges that narrow, a cluster or the whole image's, at "
        "the sizes the patch allows, seeding the matching as 'seeded' does: a part far from the camera); 'both' is "
        "'search+tetrad'. A "
        "generator after the first runs only while the best pose so far, climbed and polished, scores below "
        "search.enough_score. Default: "
        "'tetrad+seeded+windows+small' (docs/results/search.md: clutter 0.21 -> 0.46 tune, 0.04 -> 0.10 leave-out, "
        "at about 8x the time; 'small': docs/results/small.md; the seeded generator before the windows since "
        "session 26: on 1,920 fresh bench images 10 righted and 4 lost, a few per cent faster, and under "
        "search.time_budget_ms the generator that finds most is the one that runs; docs/results/latency.md)",
        "tetrad+seeded+windows+small")
    coarse_factor: int = doc("the search's coarse grid: one cell per this many pixels", 4, 1, 16)
    spread: int = doc("cells a template point may miss its edge by on the coarse grid", 1, 0, 4)
    template_points: int = doc("points per template, sampled evenly along a view's edges", 48, 8, 256)
    coarse_view_step_deg: float = doc(
        "spacing of the views the search tries (graph views nearest a golden spiral this sparse), degrees",
        25.0, 2.0, 60.0)
    angles: int = doc("in-plane angles tried per view, evenly over 360 degrees", 24, 1, 360)
    min_size_fraction: float = doc("smallest part diameter searched, share of the image diagonal", 0.2, 0.01, 2.0)
    max_size_fraction: float = doc("largest part diameter searched, share of the image diagonal", 0.75, 0.01, 4.0)
    size_step: float = doc("ratio between successive part diameters searched", 1.25, 1.01, 2.0)
    min_coarse_share: float = doc(
        "a position is scored only if this share of a template's probe points (a quarter of its points, spread "
        "along it) hit an edge (0.5 rather than 0.4: the search's kernel 0.59x the CPU on occluded images, the "
        "same poses on the tuning parts' bench scenes; docs/results/latency.md)", 0.5, 0.0, 1.0)
    hypotheses: int = doc("best distinct templates handed to the refinement", 48, 1, 256)
    distinct_fraction: float = doc(
        "templates of one view and about one angle closer than this share of their size are one", 0.2, 0.0, 1.0)
    enough_score: float = doc(
        "a generator after the first runs only while the best pose so far, climbed and polished, scores below "
        "this (0.85: on the tuning parts' bench scenes no wrong pose of the tetrads scored it after the climb "
        "where a later generator found the right one)", 0.85, 0.0, 1.01)
    seeds: int = doc("'seeded': best distinct templates matched by Kuhn-Munkres, the best-covered "
                     "'hypotheses' of them go on to the refinement", 128, 1, 1024)
    seed_window: float = doc("'seeded', 'windows': image segments within this many part radii of a seed's "
                             "centre are matched to its view", 1.2, 0.1, 4.0)
    windows: int = doc("'windows': best distinct places of the search matched as regions", 6, 1, 64)
    time_budget_ms: float = doc(
        "an image's soft deadline, milliseconds from the start of its estimate; 0: none. A generator after the "
        "first, a colour place or the larger check starts only if what it took on this estimator's recent images "
        "still fits before it with time for the last steps (the finalists' climb, the twin check), which always "
        "run, as does the first generator; the estimate's 'skipped' names what did not start. A step not yet "
        "timed counts as free, so an estimator's first image runs on until the deadline has passed. The "
        "generators that find most should come first: at 500 ms the default order kept 213 and 167 of the 226 "
        "and 172 right poses of bench images 64-79 and 80-95 (one process, two workers), 90 % of the images "
        "within 475-492 ms against 713-762; 'seeded+windows+tetrad+small' 216 and 172, at 61 ms instead of 22 "
        "for a plain clean image; the order before session 26 ('tetrad+windows+seeded+small') at 250 ms only "
        "156 of 226 (docs/results/latency.md, session 26)",
        0.0, 0.0, 60000.0)

    def __post_init__(self):
        stages = self.stages
        if not stages or any(s not in GENERATORS for s in stages) or len(set(stages)) < len(stages):
            raise ValueError(f"generators must be 'both' or some of {', '.join(GENERATORS)} joined by '+', "
                             f"each once, got {self.generators!r}")
        super().__post_init__()
        if self.max_size_fraction < self.min_size_fraction:
            raise ValueError("max_size_fraction must not be below min_size_fraction")

    @property
    def stages(self) -> tuple[str, ...]:
        """The generators in the order they run."""
        return ("search", "tetrad") if self.generators == "both" else tuple(self.generators.split("+"))


@dataclass(frozen=True)
class EstimatorParams:
    edges: EdgeParams = field(default_factory=EdgeParams)
    matching: MatchParams = field(default_factory=MatchParams)
    pose: PoseParams = field(default_factory=PoseParams)
    search: SearchParams = field(default_factory=SearchParams)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict | None) -> "EstimatorParams":
        """Nested dict (as in the YAML file) to params; unknown keys are an error, not ignored."""
        if data is not None and not isinstance(data, dict):
            raise ValueError(f"parameters must be a mapping of groups ({', '.join(cls().to_dict())}), "
                             f"got {type(data).__name__}")
        data = dict(data or {})
        groups = {f.name: f.type for f in dataclasses.fields(cls)}
        unknown = set(data) - set(groups)
        if unknown:
            raise ValueError(f"unknown parameter group(s): {', '.join(sorted(unknown))}")
        values = {}
        for group in dataclasses.fields(cls):
            default = getattr(cls(), group.name)
            overrides = data.get(group.name) or {}
            if not isinstance(overrides, dict):
                raise ValueError(f"parameter group {group.name!r} must be a mapping")
            values[group.name] = replace_checked(default, overrides, group.name)
        return cls(**values)

    @classmethod
    def load(cls, path: str | Path) -> "EstimatorParams":
        try:
            data = yaml.safe_load(Path(path).read_text())
        except FileNotFoundError:
            raise ValueError(f"parameter file {path} does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"cannot read parameter file {path}: {exc}") from None
        except yaml.YAMLError as exc:
            raise ValueError(f"parameter file {path} is not valid YAML: {one_line(exc)}") from None
        try:
            return cls.from_dict(ros_section(data))
        except ValueError as exc:
            raise ValueError(f"parameter file {path}: {exc}") from None

    def flat(self) -> dict[str, Any]:
        """``{"matching.empty_coefficient": 0.25, ...}``: the names of the ROS parameters."""
        return {f"{g}.{k}": v for g, d in self.to_dict().items() for k, v in d.items()}

    def with_flat(self, updates: dict[str, Any]) -> "EstimatorParams":
        nested: dict[str, dict] = {}
        for name, value in updates.items():
            group, _, key = name.partition(".")
            nested.setdefault(group, {})[key] = value
        merged = {g: {**d, **nested.get(g, {})} for g, d in self.to_dict().items()}
        extra = set(nested) - set(merged)
        if extra:
            raise ValueError(f"unknown parameter group(s): {', '.join(sorted(extra))}")
        return EstimatorParams.from_dict(merged)


def ros_section(data: Any) -> Any:
    """The parameters of a ROS 2 parameter file's one node (``NODE: ros__parameters: ...``,
    names nested by group or dotted) as the nested groups ``from_dict`` reads; anything
    else is returned as it is. So one file (config/learned.yaml) serves both the node's
    ``--params-file`` and the CLIs' ``--params``."""
    if not (isinstance(data, dict) and len(data) == 1):
        return data
    (section,) = data.values()
    if not (isinstance(section, dict) and list(section) == ["ros__parameters"]):
        return data
    nested: dict[str, Any] = {}
    for name, value in (section["ros__parameters"] or {}).items():
        group, dot, key = str(name).partition(".")
        if dot:
            nested.setdefault(group, {})[key] = value
        elif isinstance(value, dict) and isinstance(nested.get(name, {}), dict):
            nested.setdefault(name, {}).update(value)
        else:
            nested[name] = value  # not a group: from_dict names it
    return nested


def replace_checked(instance, overrides: dict, group: str):
    """dataclasses.replace with unknown names refused and each value checked against the
    field's type and then its range. An int is a float too, and so is a string that reads as
    one (PyYAML takes ``1e-3`` for a string, ROS parameter files for a number); nothing else
    is converted: ``"2"`` or ``2.5`` for an int, or ``"on"`` for a bool, is refused, not guessed."""
    fields = {f.name: f for f in dataclasses.fields(instance)}
    unknown = set(overrides) - set(fields)
    if unknown:
        raise ValueError(f"unknown parameter(s) in {group}: {', '.join(sorted(unknown))}")
    cast = {}
    for name, value in overrides.items():
        kind = type(getattr(instance, name))
        if kind is float and isinstance(value, (int, str)) and not isinstance(value, bool):
            try:
                value = float(value)
            except ValueError:
                pass
        if type(value) is not kind:
            raise ValueError(f"{group}.{name} must be {kind.__name__}, got {value!r}")
        cast[name] = value
    try:
        return dataclasses.replace(instance, **cast)
    except ValueError as exc:
        raise ValueError(f"{group}.{exc}") from None


def one_line(exc: Exception) -> str:
    """An exception's message on one line (YAML errors span several)."""
    return " ".join(str(exc).split())


def field_ranges() -> dict[str, tuple[float, float]]:
    """Closed range of every flat parameter name that has one."""
    return {f"{group.name}.{f.name}": f.metadata["range"]
            for group in dataclasses.fields(EstimatorParams)
            for f in dataclasses.fields(getattr(EstimatorParams(), group.name)) if "range" in f.metadata}


def field_docs() -> dict[str, str]:
    """Documentation of every flat parameter name."""
    out = {}
    for group in dataclasses.fields(EstimatorParams):
        for f in dataclasses.fields(getattr(EstimatorParams(), group.name)):
            out[f"{group.name}.{f.name}"] = f.metadata.get("doc", "")
    return out
