"""The inspection use case: a temperature field and a part file to cold dimensions, deviations and a verdict."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from services.formats.part import FORM_MEASURES, Feature, Part
from services.inspection.alignment import Alignment, align_nominal

from services.inspection.cold_equivalent import NEIGHBOURHOOD_MM, NEIGHBOURHOOD_SAMPLES, ColdGeometry, cold_equivalent
from services.inspection.deviation import (MIN_DEFECT_CELLS, MIN_DEFECT_POINTS, cell_means, find_defects,
                                          summarize_deviation, surface_deviation, surface_verdict)
from services.inspection.distance import feature_distance
from services.inspection.features import (NominalFeature, element_position_std, fit_measured, fit_nominal_feature,
                                          measure)
from services.inspection.nominal import NominalSurface
from services.inspection.point_rows import column_mean, finite_rows
from services.inspection.robust import even_subset
from services.inspection.uncertainty import (COVERAGE_FACTOR, TemperatureBudget, size_uncertainty,
                                             temperature_uncertainty)
from services.inspection.verdict import decide, overall

REPORT_VERSION = 1
_SEED_POINTS = 30000
# a diameter sees the systematic error s of two opposite sides; an ovality (Dmax - Dmin) at worst that of four, a
# pattern of two undulations per revolution raising Dmax by 2 s and lowering Dmin by 2 s (as a station's heads,
# each biased by its view angle, make it: docs/inspection.md, "All round")
_SYSTEMATIC_FACTOR = {"diameter": 2.0, "ovality": 4.0, "distance": np.sqrt(2.0)}


@dataclass(frozen=True)
class PreparedPart:
    """A part with its nominal surface and nominal feature fits, built once and reused for every scan."""

    part: Part
    nominal: NominalSurface
    features: dict[str, NominalFeature]


def prepare_part(part: Part) -> PreparedPart:
    """Build the nominal surface's distance queries and fit each feature to the nominal (a ``ValueError``
    names a feature whose region misses the nominal surface)."""
    nominal = NominalSurface(part.vertices, part.triangles)
    features = {feature.name: fit_nominal_feature(feature, nominal)
                for feature in part.definition.features if feature.type != "distance"}
    return PreparedPart(part, nominal, features)


@dataclass(frozen=True)
class Inspection:
    """What an inspection found.

    Attributes
    ----------
    report : dict
        REPORT.json (docs/inspection.md).
    cold_points : (N, 3) array
        Cold-equivalent position of every field point, world frame (NaN for points not of the part).
    deviation : (N,) float32 array
        Signed deviation from the nominal surface, mm (NaN for points not of the part).
    fallback : (N,) bool array
        Part points whose temperature came from their neighbourhood (or the part's trend), not their own.
    alignment : Alignment
        Part frame to world.
    heads : tuple of HeadPoints
        Points per head of a station's merged field (its ``head`` property); empty without one.
    """

    report: dict[str, Any]
    cold_points: np.ndarray
    deviation: np.ndarray
    fallback: np.ndarray
    alignment: Alignment
    heads: tuple[HeadPoints, ...] = ()


@dataclass(frozen=True)
class HeadPoints:
    """What one head of a station contributed to the inspected field: its points and, of them, the part's."""

    head: int
    points: int
    part_points: int


def head_points(head: np.ndarray, part: np.ndarray) -> tuple[HeadPoints, ...]:
    """Points per head (``head``: the field's per-point head index) and the part's among them (``part``: bool)."""
    head = np.asarray(head)
    if not (np.issubdtype(head.dtype, np.integer)
            or (np.issubdtype(head.dtype, np.floating) and np.all(np.isfinite(head)) and np.all(head == np.round(head)))):
        raise ValueError(f"the field's 'head' property must hold head indices (integers); got {head.dtype} values")
    if len(head) and head.min() < 0:
        raise ValueError(f"the field's 'head' property must hold head indices (0 or more); got {head.min():g}")
    heads, inverse, counts = np.unique(head.astype(np.int64), return_inverse=True, return_counts=True)
    on_part = np.bincount(inverse.ravel(), weights=part, minlength=len(heads)).astype(np.int64)
    return tuple(HeadPoints(int(h), int(n), int(m)) for h, n, m in zip(heads, counts, on_part))


def _budget(part: Part) -> TemperatureBudget:
    budget = part.definition.uncertainty
    return TemperatureBudget(emissivity=budget.emissivity, emissivity_uncertainty=budget.emissivity_uncertainty,
                             calibration_fraction=budget.calibration_fraction,
                             calibration_min_k=budget.calibration_min_k, netd_k=budget.netd_k)


MIN_PART_POINTS = 20
"""Fewer measured points on the aligned nominal surface than this are no part: no verdict from them."""
MAX_NORMAL_ANGLE_DEG = 60.0
"""A point near the aligned nominal is the part's only if its measured normal makes at most this angle with the
nominal's outward normal at its match (``agrees_with_nominal``): the flank of a dent or bulge is tilted by its
slope, tens of degrees at most; a fixture, the support or a misplaced part's overhang meets it at more."""


def inspect_field(*, field: dict[str, np.ndarray], part: Part | PreparedPart) -> Inspection:
    """Inspect one measured part: cold-equivalent geometry, alignment, features, surface deviation, verdicts.

    Parameters
    ----------
    field : dict of 1-D arrays
        A temperature field (``x, y, z`` world mm and ``temperature`` degrees C, NaN where unseen),
        as ``thermofield field`` writes it; it may hold other surfaces than the part.
    part : Part or PreparedPart
        The part file, loaded (prepare it once with ``prepare_part`` to inspect many scans).

    Returns
    -------
    Inspection
        The report and the per-point results.

    Notes
    -----
    1. Points at least ``segmentation.min_temperature_c`` hot, and the points without a temperature
       within 25 mm of them (``NEIGHBOURHOOD_MM``), seed the part; their cold equivalents
       (``cold_equivalent``) are aligned to the nominal (``align_nominal``), each matched only to nominal
       surface that faces the camera which measured it (the field's normals ``nx, ny, nz``, when it has them).
    2. The expansion's fixed point is moved to the nominal's volume centroid as aligned, every
       point with a temperature at least that hot or none is made cold-equivalent, the alignment is
       refined, and the points within ``segmentation.max_distance_mm`` of the nominal surface whose
       normals agree with the nominal's there (``agrees_with_nominal``: at most ``MAX_NORMAL_ANGLE_DEG``
       apart) are the part's; in a field with normals, a point without one (the cloud's border) is not.
    3. Each feature is fitted to the part's cold points in its region (part frame) and to the same
       points hot; its deviation from nominal gets an expanded uncertainty (k = 2) from the budget
       (``size_uncertainty``) and a verdict (``decide``).
    4. The surface's verdict (``surface_verdict``) applies ISO 14253-1's rule to patches of the 1 mm
       cell means: a defect needs 10 connected cells and 20 points (``MIN_DEFECT_CELLS``,
       ``MIN_DEFECT_POINTS``); cells with points that took their neighbourhood's temperature are judged
       with the fallback temperature uncertainty (``_surface_result``).
    """
    prepared = part if isinstance(part, PreparedPart) else prepare_part(part)
    part = prepared.part
    definition = part.definition
    points, temperature, finite, hot = _field_points(field, definition.segmentation.min_temperature_c)
    located = _locate_part(points, temperature, finite, hot, prepared, _field_normals(field))
    member, candidates = located.member, located.candidates

    n = len(points)
    cold_points = np.full((n, 3), np.nan)
    cold_points[candidates[member]] = located.cold.points[member]
    deviation_out = np.full(n, np.nan, dtype=np.float32)
    deviation_out[candidates[member]] = located.deviation[member]
    fallback = np.zeros(n, dtype=bool)
    fallback[candidates[member]] = located.cold.fallback[member]

    budget = _budget(part)
    material_fraction = definition.uncertainty.material_fraction
    if material_fraction is None:
        material_fraction = part.material.relative_uncertainty
    results = _measure_features(prepared, located, points, budget, material_fraction)
    surface = _surface_result(located.in_part, located.deviation[member], located.used_temperature,
                              located.used_fallback, part, budget, material_fraction)
    heads = head_points(field["head"], np.isfinite(deviation_out)) if "head" in field else ()
    report = _report(part, results, surface, located, material_fraction)
    if heads:
        report["heads"] = [asdict(head) for head in heads]
    return Inspection(report=report, cold_points=cold_points, deviation=deviation_out, fallback=fallback,
                      alignment=located.alignment, heads=heads)


def _field_normals(field: dict[str, np.ndarray]) -> np.ndarray | None:
    """The field's point normals (``nx, ny, nz``, toward the camera that measured each point), None without them."""
    if not all(name in field for name in ("nx", "ny", "nz")):
        return None
    return np.column_stack([field["nx"], field["ny"], field["nz"]]).astype(np.float64)


def _field_points(field: dict[str, np.ndarray], min_temperature_c: float):
    """The field's points and temperatures, the finite points and the hot ones (at least ``min_temperature_c``);
    a field without temperatures or without a hot part is refused."""
    missing = [name for name in ("x", "y", "z", "temperature") if name not in field]
    if missing:
        raise ValueError(f"The field lacks the properties {missing}; inspect a temperature field "
                         "(thermofield field or fuse).")
    points = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float64)
    temperature = np.asarray(field["temperature"], dtype=np.float64)
    finite = finite_rows(points)
    hot = finite & (temperature >= min_temperature_c)
    if hot.sum() < 100:
        with_temperature = int(np.count_nonzero(finite & np.isfinite(temperature)))
        if with_temperature < 100:
            raise ValueError(f"Only {with_temperature} of the field's {int(finite.sum())} points have a temperature: "
                             "the thermal camera saw too little of the surface alone (mixed edge pixels get none, "
                             "docs/temperature-field.md); a part cannot be found or judged without them.")
        raise ValueError(f"Only {int(hot.sum())} points are at least {min_temperature_c:g} "
                         "degC hot; the field shows no hot part (segmentation.min_temperature_c in the part file).")
    return points, temperature, finite, hot


@dataclass(frozen=True)
class _LocatedPart:
    """The part found in a field: the candidate points (indices into the field), their cold equivalents, the
    alignment to the nominal, each candidate's deviation and which are the part's (``member``)."""

    candidates: np.ndarray
    cold: ColdGeometry
    alignment: Alignment
    cold_part_frame: np.ndarray
    deviation: np.ndarray
    member: np.ndarray
    turned: int = 0
    """Points within the segmentation distance left out because their normals disagree with the nominal's."""
    without_normal: int = 0
    """Points within the segmentation distance left out because the field gives them no normal."""

    @property
    def in_part(self) -> np.ndarray:
        return self.cold_part_frame[self.member]

    @property
    def part_points(self) -> np.ndarray:
        return self.candidates[self.member]

    @property
    def used_temperature(self) -> np.ndarray:
        return self.cold.temperature[self.member]

    @property
    def used_fallback(self) -> np.ndarray:
        return self.cold.fallback[self.member]


def _locate_part(points: np.ndarray, temperature: np.ndarray, finite: np.ndarray, hot: np.ndarray,
                 prepared: PreparedPart, normals: np.ndarray | None = None) -> _LocatedPart:
    """Steps 1 and 2 of :func:`inspect_field`: seed, make cold-equivalent, align, and keep the points near the
    nominal surface; too few of them is no part."""
    part = prepared.part
    max_distance = part.definition.segmentation.max_distance_mm
    # the part: its hot points and the points without a temperature beside them (the fusion's mixed edge
    # pixels, the thermal camera's blind spots), which a one-sided view of a thin part may need to pin its pose
    seed = even_subset(np.flatnonzero(hot | _beside(points, hot, finite & ~np.isfinite(temperature))), _SEED_POINTS)
    first = cold_equivalent(points[seed], temperature[seed], part.material)
    coarse = align_nominal(first.points, prepared.nominal, max_distance_mm=max_distance, polish=False,
                           normals=None if normals is None else normals[seed])
    centre = coarse.to_world(prepared.nominal.centroid[None])[0]

    candidates = np.flatnonzero(finite & (hot | ~np.isfinite(temperature)))
    cold = cold_equivalent(points[candidates], temperature[candidates], part.material, centre=centre)
    is_seed = np.zeros(len(points), dtype=bool)
    is_seed[seed] = True
    hot_seed = is_seed[candidates]
    alignment = align_nominal(cold.points[hot_seed], prepared.nominal, max_distance_mm=max_distance,
                              start=coarse.matrix, normals=None if normals is None else normals[candidates[hot_seed]])
    cold_part_frame = alignment.to_part(cold.points)
    deviation = surface_deviation(cold_part_frame, prepared.nominal)
    near = np.abs(deviation) <= max_distance
    member = near.copy()
    if normals is not None and near.any():
        near_index = np.flatnonzero(near)
        # a rotation turns normals as it turns points: world to part frame is the transpose
        member[near_index] = agrees_with_nominal(cold_part_frame[near_index],
                                                 normals[candidates[near_index]] @ alignment.matrix[:3, :3],
                                                 prepared.nominal)
    if np.count_nonzero(member) < MIN_PART_POINTS:
        raise ValueError(f"only {np.count_nonzero(member)} measured points lie within {max_distance:g} mm of the "
                         f"nominal surface once aligned, facing as it does (at least {MIN_PART_POINTS} needed): the "
                         "part is not in the field (hidden, lost to the glow, or not this part type)")
    unknown = near & ~member
    if normals is not None:
        unknown &= ~np.isfinite(normals[candidates]).all(axis=1)
    return _LocatedPart(candidates, cold, alignment, cold_part_frame, deviation, member,
                        int(np.count_nonzero(near & ~member & ~unknown)), int(np.count_nonzero(unknown)))


def agrees_with_nominal(points_part: np.ndarray, normals_part: np.ndarray, nominal: NominalSurface,
                        max_angle_deg: float = MAX_NORMAL_ANGLE_DEG) -> np.ndarray:
    """Whether each measured point's normal agrees with the nominal surface's outward normal at its match.

    Parameters
    ----------
    points_part : (N, 3) array
        Cold-equivalent points in the part frame, near the nominal surface.
    normals_part : (N, 3) array
        Their measured normals in the part frame, facing the camera that measured each (a reconstruction's
        ``nx, ny, nz``, a station's merged field's each toward its own head); NaN where unknown.
    nominal : NominalSurface
        The nominal part.
    max_angle_deg : float
        The largest angle between the two normals of a point that is the part's.

    Returns
    -------
    (N,) bool array
        True where the angle is at most ``max_angle_deg``; False where the normal is unknown.

    Notes
    -----
    The rule: a point at distance d from the nominal is read as the part's surface displaced by d along the
    nominal's normal n at its match (the gradient of the signed distance, ``signed_distance_gradient``: the
    closest triangle's normal on a face, (p - q) / d off an edge). That reading holds only where the measured
    surface runs nearly parallel to the nominal there: a dent or bulge of depth h and width w tilts its flanks
    by about atan(h / w) (a Gaussian one of standard deviation s at most atan(0.61 h / s): 22 degrees for a 4 mm
    bump of s = 6 mm, the zoo's steepest out-of-tolerance one), and its deepest point, the one that decides its
    depth, is not tilted at all. A point whose normal makes more than ``max_angle_deg`` (60 degrees) with n
    belongs to another surface that happens to pass within the segmentation distance: a fixture or the support
    meeting the part at an angle (the support's top face seen from the camera faces the part's underside, the
    angle above 90 degrees), or the overhang of a part misplaced along a direction its view does not pin (a
    tube's wall beyond the nominal's end, matched to the rim's edge at 90 degrees). Taken as the part's, those
    points made patches of cells at up to the segmentation distance (+4.9 to +5.0 mm) and rejected parts in
    tolerance. A measured normal is the cross product of the point map's central differences
    (``surface_normals`` in services/structured_light/reconstruct.py), a few degrees off on a smooth surface, so
    60 degrees leaves more than 30 degrees of margin on either side. The normals are compared with their signs:
    a camera sees the outside of the part's surface, so its measured normal and the nominal's outward one agree
    on every face it can see (a bore's wall included), while a support under the part, seen from above, faces
    the part's underside (the angle near 180 degrees): the alignment's facing test (``align_nominal``) is the
    same comparison at its physical bound of 90 degrees.

    What the rule cannot see: a surface that really belongs to the part but stands steeply on the nominal (a
    fin of flash, a step where the part is longer than nominal) is dropped as foreign rather than judged, but
    for its points whose normals agree (a fin's tip, a longer end's face); the count of points dropped is in
    the report (``segmentation.turned_points``; ``points_without_normal`` those left out for want of a normal)
    so that such a part can be told from a clean one.

    A point whose normal is unknown (NaN) does not agree: in a field with normals these are the points at
    the border of the camera's point map (a pixel missing one of its four neighbours: a depth edge, a
    shadow's rim), where the decoded point mixes two surfaces (docs/zoo.md, S1) and nothing tells the
    part's from a foreign surface's; the turned overhang of a slid part ends in a line of them. A field without
    normals is segmented by the distance alone (``_locate_part`` does not call this).
    """
    _, gradient = nominal.signed_distance_gradient(points_part)
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = (np.einsum("ij,ij->i", normals_part, gradient)
                  / (np.linalg.norm(normals_part, axis=1) * np.linalg.norm(gradient, axis=1)))
    return cosine >= np.cos(np.radians(max_angle_deg))


@dataclass(frozen=True)
class _ElementFit:
    """A plane, cylinder or sphere fitted to a region's points cold (judged) and hot, with the points, their mean
    temperature, its uncertainty and how many points the region held."""

    cold: Any
    hot: Any
    cold_points: np.ndarray
    hot_points: np.ndarray
    mean_t: float
    u_t: float
    count: int


def _measure_features(prepared: PreparedPart, located: _LocatedPart, points: np.ndarray,
                      budget: TemperatureBudget, material_fraction: float) -> list[dict[str, Any]]:
    """Step 3 of :func:`inspect_field`: each feature fitted cold and hot, then the distances between them."""
    part = prepared.part
    definition = part.definition
    in_part, part_points, alignment = located.in_part, located.part_points, located.alignment
    used_temperature, used_fallback = located.used_temperature, located.used_fallback
    fits: dict[str, _ElementFit] = {}
    by_region: dict[tuple, _ElementFit] = {}
    results = []
    for feature in definition.features:
        if feature.type == "distance":
            continue
        key = (feature.type, tuple(feature.region.min), tuple(feature.region.max))
        if key not in by_region:  # features of one element (a cylinder's diameter and ovality) share its fits
            inside = np.flatnonzero(feature.region.contains(in_part))
            fitted = even_subset(inside)  # the points the fits keep, drawn before their positions are gathered
            try:
                cold_element = fit_measured(prepared.features[feature.name], in_part[fitted])
            except ValueError as error:  # the view may not show every feature: say so, decide nothing
                if feature.measure is not None:
                    results.append(_unmeasured(feature, str(error)))
                continue
            stretch = float(np.mean(1 + part.material.strain(used_temperature[inside])))
            hot_points = alignment.to_part(points[part_points[fitted]])
            mean_t = float(np.mean(used_temperature[inside]))
            by_region[key] = _ElementFit(
                cold_element, fit_measured(prepared.features[feature.name], hot_points, stretch), in_part[fitted],
                hot_points, mean_t, _temperature_std(mean_t, budget, float(np.mean(used_fallback[inside])),
                                                     definition.uncertainty.fallback_temperature_k), len(inside))
        fit = fits[feature.name] = by_region[key]
        if feature.measure is None:
            continue
        try:
            cold = measure(feature, fit.cold, fit.cold_points)
            hot = measure(feature, fit.hot, fit.hot_points)
        except ValueError as error:  # ovality from a view that does not go all round
            results.append(_unmeasured(feature, str(error)))
            continue
        results.append(_feature_result(feature, hot.value, cold.value, cold.std, fit.count, fit.mean_t, fit.u_t,
                                       part, material_fraction))
    for feature in definition.features:
        if feature.type != "distance":
            continue
        if any(name not in fits for name in feature.between):
            results.append(_unmeasured(feature, f"{' or '.join(feature.between)} could not be fitted"))
            continue
        a, b = (fits[name] for name in feature.between)
        cold_value = feature_distance(a.cold, b.cold)
        hot_value = feature_distance(a.hot, b.hot)
        fit_std = float(np.hypot(element_position_std(a.cold), element_position_std(b.cold)))
        results.append(_feature_result(feature, hot_value, cold_value, fit_std, a.cold.count + b.cold.count,
                                       (a.mean_t + b.mean_t) / 2, max(a.u_t, b.u_t), part, material_fraction))
    return results


def _report(part: Part, results: list[dict[str, Any]], surface: dict[str, Any], located: _LocatedPart,
            material_fraction: float) -> dict[str, Any]:
    """Step 4's report (docs/inspection.md, REPORT.json): the overall verdict, features, surface, alignment,
    temperatures and the budget."""
    definition = part.definition
    used_temperature, alignment = located.used_temperature, located.alignment
    return {
        "version": REPORT_VERSION,
        "part": definition.name,
        "verdict": overall([result["verdict"] for result in results] + [surface["verdict"]]),
        "features": results,
        "surface": surface,
        "alignment": {"rms_mm": alignment.rms_mm, "inlier_fraction": alignment.inlier_fraction,
                      "matrix": alignment.matrix.tolist()},
        "segmentation": {"points": int(located.member.sum()), "turned_points": located.turned,
                         "points_without_normal": located.without_normal,
                         "max_distance_mm": definition.segmentation.max_distance_mm,
                         "max_normal_angle_deg": MAX_NORMAL_ANGLE_DEG},
        "temperature": {"points": int(located.member.sum()), "fallback_points": int(located.used_fallback.sum()),
                        "mean_c": float(np.mean(used_temperature)), "min_c": float(np.min(used_temperature)),
                        "max_c": float(np.max(used_temperature)),
                        "trend_c": located.cold.trend.tolist(), "material": part.material.name,
                        "material_source": part.material.source},
        "budget": {**definition.uncertainty.model_dump(), "material_fraction": material_fraction,
                   "coverage_factor": COVERAGE_FACTOR},
    }


def _beside(points: np.ndarray, hot: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """The ``unknown`` points within ``NEIGHBOURHOOD_MM`` of a ``hot`` one (of ``NEIGHBOURHOOD_SAMPLES`` of those,
    evenly drawn)."""
    beside = np.zeros(len(points), dtype=bool)
    wanted = np.flatnonzero(unknown)
    if len(wanted):
        tree = cKDTree(points[even_subset(np.flatnonzero(hot), NEIGHBOURHOOD_SAMPLES)])
        beside[wanted] = np.isfinite(tree.query(points[wanted], distance_upper_bound=NEIGHBOURHOOD_MM)[0])
    return beside


def _temperature_std(mean_t: float, budget: TemperatureBudget, fallback_fraction: float, fallback_k: float) -> float:
    """The feature's temperature uncertainty: the camera's at its mean temperature, plus the fallback points' share."""
    camera = temperature_uncertainty(mean_t, budget)["total"]
    return float(np.hypot(camera, fallback_fraction * fallback_k))


def _unmeasured(feature: Feature, reason: str) -> dict[str, Any]:
    return {"name": feature.name, "type": feature.type, "measure": feature.measure, "hot": None, "cold": None,
            "nominal": feature.nominal, "deviation": None, "tolerance": list(feature.tolerance), "uncertainty": None,
            "verdict": "NotDecidable", "points": 0, "error": reason}


def _feature_result(feature: Feature, hot: float, cold: float, fit_std: float, count: int, mean_t: float,
                    u_t: float, part: Part, material_fraction: float) -> dict[str, Any]:
    systematic = (part.definition.uncertainty.structured_light_systematic_mm
                  * _SYSTEMATIC_FACTOR.get(feature.measure, 1.0))
    terms = size_uncertainty(cold, mean_t, u_t, part.material, material_fraction, fit_std, systematic)
    deviation = cold - feature.nominal
    lower, upper = feature.tolerance
    # a form error is never negative: a lower limit admitting every value down to 0 is no limit (the usual
    # one-sided form tolerance of ISO 1101, [0, t]), and an interval reaching below it must not be NotDecidable
    one_sided = feature.measure in FORM_MEASURES and feature.nominal + lower <= 0
    limits = (-np.inf if one_sided else lower, upper)
    return {"name": feature.name, "type": feature.type, "measure": feature.measure, "hot": hot, "cold": cold,
            "nominal": feature.nominal, "deviation": deviation, "tolerance": list(feature.tolerance),
            "uncertainty": terms["expanded"], "verdict": decide(deviation, limits, terms["expanded"]),
            "points": count, "temperature_c": mean_t, "temperature_uncertainty_k": u_t,
            "standard_uncertainties": {key: terms[key] for key in ("fit", "structured_light", "temperature",
                                                                   "material", "combined")}}


def _surface_result(in_part: np.ndarray, deviation: np.ndarray, temperature: np.ndarray, fallback: np.ndarray,
                    part: Part, budget: TemperatureBudget, material_fraction: float) -> dict[str, Any]:
    """The surface's deviation summary, defects and verdict.

    The 1 mm cells of the deviation map give the extremes, the defects and the verdict
    (``surface_verdict``: patches of ``MIN_DEFECT_CELLS`` cells holding ``MIN_DEFECT_POINTS`` points). A
    cell that holds a point whose temperature came from its neighbourhood (no reading of its own, or a
    mixed edge pixel's, which the fusion left NaN) is judged with the fallback temperature uncertainty.
    """
    definition = part.definition
    tolerance = tuple(definition.surface_tolerance)
    summary = summarize_deviation(deviation, tolerance)
    cells = cell_means(in_part, deviation)
    defects = find_defects(cells, definition.defect_threshold_mm)
    lowest, highest = (float(cells.mean.min()), float(cells.mean.max())) if len(cells.mean) else (np.nan, np.nan)
    # a cell's deviation: its mean noise, the structured light's systematic error and, far from the centre,
    # the temperature and table errors acting on its distance from the centre
    mean_t = float(np.mean(temperature))
    if len(in_part):
        offset = in_part - column_mean(in_part)
        reach = float(np.sqrt(np.max(np.einsum("ij,ij->i", offset, offset))))
    else:
        reach = 0.0
    u_t = temperature_uncertainty(mean_t, budget)["total"]
    noise = definition.uncertainty.structured_light_noise_mm  # a cell of one point, at the sparsest
    systematic = definition.uncertainty.structured_light_systematic_mm
    uncertainty = size_uncertainty(reach, mean_t, u_t, part.material, material_fraction, noise,
                                   systematic)["expanded"]
    fallback_uncertainty = size_uncertainty(
        reach, mean_t, float(np.hypot(u_t, definition.uncertainty.fallback_temperature_k)), part.material,
        material_fraction, noise, systematic)["expanded"]
    if len(cells.mean):
        # the cells holding a point of estimated temperature (every part point is binned: its deviation is finite)
        estimated = np.zeros(len(cells.keys), dtype=bool)
        if fallback.any():
            estimated[np.searchsorted(cells.keys, np.unique(cells.point_keys[fallback]))] = True
        verdict = surface_verdict(cells, tolerance, np.where(estimated, fallback_uncertainty, uncertainty))
    else:
        verdict = "NotDecidable"
    return {"points": summary.points, "mean": summary.mean, "std": summary.std, "min": summary.min,
            "max": summary.max, "fraction_outside": summary.fraction_outside, "tolerance": list(tolerance),
            "cell_min": lowest, "cell_max": highest, "uncertainty": uncertainty, "verdict": verdict,
            "fallback_uncertainty": fallback_uncertainty,
            "evidence": {"cell_mm": cells.cell_mm, "min_cells": MIN_DEFECT_CELLS, "min_points": MIN_DEFECT_POINTS},
            "defects": [{"center": defect.center.tolist(), "depth": defect.depth_mm, "area_mm2": defect.area_mm2,
                         "points": defect.points} for defect in defects]}


def deviation_cloud(field: dict[str, np.ndarray], inspection: Inspection, part: Part) -> dict[str, np.ndarray]:
    """The field with float32 ``deviation`` (mm, NaN off the part) and RGB from the deviation map."""
    from services.inspection.deviation import deviation_colors

    rgb = deviation_colors(inspection.deviation, tuple(part.definition.surface_tolerance))
    cloud = {name: values for name, values in field.items() if name not in ("deviation", "red", "green", "blue")}
    cloud.update(deviation=inspection.deviation, red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    return cloud


def cold_cloud(field: dict[str, np.ndarray], inspection: Inspection, part: Part) -> dict[str, np.ndarray]:
    """The part's points at their cold-equivalent positions (world frame) with temperature, fallback flag,
    deviation and deviation colours, and the head that measured each where the field says (``head``)."""
    from services.inspection.deviation import deviation_colors

    member = np.isfinite(inspection.deviation)
    cold = inspection.cold_points[member]
    rgb = deviation_colors(inspection.deviation[member], tuple(part.definition.surface_tolerance))
    return {"x": cold[:, 0].astype(np.float32), "y": cold[:, 1].astype(np.float32), "z": cold[:, 2].astype(np.float32),
            "temperature": np.asarray(field["temperature"], dtype=np.float32)[member],
            "temperature_fallback": inspection.fallback[member].astype(np.uint8),
            "deviation": inspection.deviation[member], "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2],
            **({"head": np.asarray(field["head"])[member]} if "head" in field else {})}


def _json_safe(value: Any) -> Any:
    """Non-finite floats as None (JSON has no NaN), numpy scalars as Python numbers, recursively."""
    if isinstance(value, dict):
        return {key: _json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(item) for item in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def report_json(report: dict[str, Any]) -> str:
    """REPORT.json text: indented, strict JSON (non-finite numbers as null)."""
    import json

    return json.dumps(_json_safe(report), indent=2, allow_nan=False) + "\n"
