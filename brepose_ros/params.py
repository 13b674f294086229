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


def doc(text: str, default: Any) -> Any:
    """A dataclass field with its default and its documentation in ``metadata["doc"]``."""
    return field(default=default, metadata={"doc": text})


@dataclass(frozen=True)
class EdgeParams:
    """Every threshold of the image edge stage; lengths in pixels unless named ``*_fraction``."""

    detector: str = doc("'hough' (Canny + HoughLinesP, the paper's method) or 'lsd' (OpenCV LSD)", "hough")
    blur_size: int = doc("odd Gaussian kernel size before edge detection; 1 disables the blur", 5)
    blur_sigma: float = doc("Gaussian sigma, pixels; 0 derives it from blur_size", 0.0)
    canny_noise_factor: float = doc("Canny high threshold in units of the gradient noise level (median gradient / 1.18)", 5.0)
    canny_low_ratio: float = doc("Canny low threshold as a share of the high one", 0.4)
    canny_min_high: float = doc("floor of the Canny high threshold (Sobel magnitude of a 0..255 image) for noise-free images", 6.0)
    hough_rho: float = doc("HoughLinesP distance resolution, pixels", 1.0)
    hough_theta_deg: float = doc("HoughLinesP angle resolution, degrees", 1.0)
    hough_vote_ratio: float = doc("HoughLinesP accumulator threshold as a share of the minimum line length", 0.5)
    raw_min_length_fraction: float = doc(
        "shortest raw segment before merging (HoughLinesP minLineLength; shorter LSD pieces are dropped), "
        "share of the image diagonal", 0.015)
    hough_max_gap: float = doc("largest gap HoughLinesP bridges inside one segment, pixels", 3.0)
    merge_angle_deg: float = doc("pieces of one edge differ in direction by at most this, degrees", 2.0)
    merge_distance: float = doc("both end points of a piece lie this close to the edge's fitted line, pixels", 2.0)
    merge_gap: float = doc("largest gap along the line between pieces of one edge, pixels", 15.0)
    refine: bool = doc("refit each merged Hough segment to the Canny pixels along it and extend it over them", True)
    min_length_fraction: float = doc("merged segments shorter than this share of the image diagonal are dropped", 0.03)
    max_segments: int = doc("at most this many merged segments are kept, longest first", 200)

    def __post_init__(self):
        if self.detector not in DETECTORS:
            raise ValueError(f"detector must be one of {DETECTORS}, got {self.detector!r}")
        if self.blur_size < 1 or self.blur_size % 2 == 0:
            raise ValueError(f"blur_size must be a positive odd integer, got {self.blur_size}")
        positive = ("canny_noise_factor", "canny_min_high", "hough_rho", "hough_theta_deg",
                    "hough_vote_ratio", "merge_angle_deg", "max_segments")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 < self.canny_low_ratio <= 1:
            raise ValueError(f"canny_low_ratio must be in (0, 1], got {self.canny_low_ratio}")
        non_negative = ("blur_sigma", "raw_min_length_fraction", "hough_max_gap",
                        "merge_distance", "merge_gap", "min_length_fraction")
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)}")


@dataclass(frozen=True)
class MatchParams:
    """Tetrad metric space and bipartite matching (seed paper sections 3 and 6)."""

    weight_length: float = doc("weight of the length difference in the tetrad distance", 1.0)
    weight_midpoint: float = doc("weight of the midpoint difference (length and angle of the midpoint)", 1.0)
    weight_orientation: float = doc("weight of the orientation difference (angle of the perpendicular), radians", 0.5)
    weight_perpendicular: float = doc("weight of the perpendicular foot-point difference (length and angle of the perpendicular)", 0.5)
    empty_coefficient: float = doc("distance of an empty element, as a share of the largest pair distance; pairs farther than twice this are left unmatched", 0.25)
    nearest_threshold: float = doc("pairs closer than this share of the empty distance form the nearest group", 0.5)
    shortlist_size: int = doc("(view, rotation) pairs per region kept by the chamfer pre-filter for Kuhn-Munkres", 48)
    rotation_candidates: int = doc("peaks of the orientation correlation tried per view, each also turned by 180 degrees", 2)
    coverage_tolerance: float = doc("distance (normalised units) within which aligned edges cover each other when ranking views", 0.04)
    max_model_segments: int = doc("longest view segments used in matching", 60)
    max_image_segments: int = doc("longest image segments used in matching per region", 90)
    max_regions: int = doc("candidate image regions (whole image, edge clusters) matched per image", 6)
    cluster_gap_fraction: float = doc(
        "segments whose end points lie closer than this share of the image diagonal chain into one cluster "
        "(a candidate region); as long as the shortest segment kept (edges.min_length_fraction), so that the "
        "edges of one part meeting at its corners chain, while objects apart by more stay apart", 0.03)
    hypotheses: int = doc("best-covered (view, rotation) hypotheses per region turned into poses and verified", 6)
    workers: int = doc("worker threads that split each region's batch of (view, rotation) jobs; 1 by default: the batched steps are short and mostly hold the GIL, and 2 threads measured no faster (bench/latency.py)", 1)


@dataclass(frozen=True)
class PoseParams:
    """Metric pose, refinement and the found / not-found decision."""

    refine_iterations: int = doc("re-match and refine rounds of every hypothesis; 0 keeps the first pose from the view", 6)
    climb_candidates: int = doc("best-scoring refined hypotheses that go on to the search over neighbouring views", 2)
    view_search_steps: int = doc("steps of the hill-climb over neighbouring aspect-graph views; 0 turns it off", 4)
    inlier_pixels: float = doc("distance of a projected model edge to an image edge still counted as found, pixels", 2.0)
    min_size_pixels: float = doc("smallest diagonal of the projected part, pixels; smaller poses score 0", 40.0)
    min_score: float = doc("a pose with a lower score is reported as not found", 0.6)
    warn_error_ratio: float = doc("diagnostics turn WARN above this error ratio", 0.5)


@dataclass(frozen=True)
class EstimatorParams:
    edges: EdgeParams = field(default_factory=EdgeParams)
    matching: MatchParams = field(default_factory=MatchParams)
    pose: PoseParams = field(default_factory=PoseParams)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict | None) -> "EstimatorParams":
        """Nested dict (as in the YAML file) to params; unknown keys are an error, not ignored."""
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
        except yaml.YAMLError as exc:
            raise ValueError(f"parameter file {path} is not valid YAML: {exc}") from None
        return cls.from_dict(data)

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


def replace_checked(instance, overrides: dict, group: str):
    """dataclasses.replace with unknown names refused and values cast to the field's type."""
    fields = {f.name: f for f in dataclasses.fields(instance)}
    unknown = set(overrides) - set(fields)
    if unknown:
        raise ValueError(f"unknown parameter(s) in {group}: {', '.join(sorted(unknown))}")
    cast = {}
    for name, value in overrides.items():
        kind = type(getattr(instance, name))
        try:
            cast[name] = kind(value) if kind in (int, float, bool, str) else value
        except (TypeError, ValueError):
            raise ValueError(f"{group}.{name} must be {kind.__name__}, got {value!r}") from None
    return dataclasses.replace(instance, **cast)


def field_docs() -> dict[str, str]:
    """Documentation of every flat parameter name."""
    out = {}
    for group in dataclasses.fields(EstimatorParams):
        for f in dataclasses.fields(getattr(EstimatorParams(), group.name)):
            out[f"{group.name}.{f.name}"] = f.metadata.get("doc", "")
    return out
