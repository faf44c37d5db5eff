"""The scene zoo: the real commands over many random scenes, and the distributions of what they get right.

Run (the reporting seeds, held out; about half a minute per scene and job on this machine):

    nice -n 10 .venv/bin/python experiments/zoo.py --seeds 1000-1229 --jobs 2 \\
        --json zoo-results.json --markdown docs/zoo.md

Seeds (services/simulation/zoo.py): TUNING seeds 0..99 may be used to choose thresholds and defaults
and are never reported; REPORTING seeds 1000..1229 are held out, never tuned on, and are what
docs/zoo.md reports. ``--seeds`` takes ranges and single seeds, ``1000-1199,1300``; asking to report
a tuning seed into docs needs ``--allow-tuning`` (then the table says so).

Per scene (``zoo_scene(seed)``): the simulated station films the scene (``SimulatedStation`` behind a
``Station``, automatic exposure, the project's default sequence closed by a black frame), then the
use cases that the commands run: ``reconstruct_capture`` (``thermofield reconstruct``), ``fuse_field``
(``thermofield field``), ``inspect_part`` with the scene's part file (``thermofield inspect``) and
``register_pair`` of the thermal frame onto the white frame (``thermofield register``). It scores:

- point error: distance of each point from the true surface point at its camera pixel's centre ray
  (a pixel whose centre ray misses every surface counts as infinitely wrong); per scene the median,
  95th percentile and worst, and the wrong-point rate (share of points more than 1 mm off);
- coverage: share of the pixels lit by the projector and seen by the camera, whose 8-neighbours are
  lit and see the same surface (a pixel straddling an edge belongs to neither), that have a point;
  also on the part alone;
- temperature error: |field temperature - true surface temperature| at the part's points that have a
  temperature (median, 95th percentile), and the share of the part's points given one;
- cold-diameter error: the report's cold diameter (or length, for boxes) minus the true cold value;
- the verdict against the truth (OK for an in-tolerance part, NotOK otherwise);
- registration: the registration's matrix maps the thermal pixel of each part point the thermal and
  visible cameras both see to a visible pixel; the median distance from the true visible pixel, next
  to that of the best similarity fitted to the true correspondences (parallax leaves no exact one).

Each stage of a scene (``STAGES``: film, reconstruct, field, inspect, register) is cached in ``--cache`` on
its own, under the seed and a key of the code the stage can run and of its input stage's key
(:func:`stage_keys`): a fix of the inspection re-runs ``inspect`` on the cached frames, cloud and field, not
the rendering. ``--stages film`` renders scenes into the cache and analyses nothing.
"""

from __future__ import annotations

import os

if __name__ == "__main__":  # run as the command (not imported by a test): before numpy and numba are imported
    for _variable in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_variable, "1")  # one thread per job: --jobs sets the parallelism

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from concurrent.futures import ProcessPoolExecutor, as_completed  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from services.simulation.zoo import REPORTING_SEEDS, TUNING_SEEDS, zoo_scene  # noqa: E402

WRONG_MM = 1.0
RESULT_VERSION = 1
_BEGIN, _END = "<!-- zoo-table:begin -->", "<!-- zoo-table:end -->"


def cached_scene_parser(description: str, modes: tuple[str, ...]) -> argparse.ArgumentParser:
    """The arguments of the scripts that study this script's cached scenes (zoo_alignment, zoo_segmentation):
    a mode, --seeds, --json and --cache."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("mode", choices=modes)
    parser.add_argument("--seeds", required=True, help="seeds and ranges, e.g. 0-99 or 1006,1020")
    parser.add_argument("--json", required=True, type=Path)
    parser.add_argument("--cache", type=Path, default=None, help="experiments/zoo.py's cache (default its own)")
    return parser


def parse_seeds(text: str) -> list[int]:
    """``1000-1199,1300`` -> [1000, ..., 1199, 1300]."""
    seeds: list[int] = []
    for piece in text.split(","):
        piece = piece.strip()
        if not piece:
            continue
        first, _, last = piece.partition("-")
        try:
            low, high = int(first), int(last or first)
        except ValueError:
            raise ValueError(f"--seeds: {piece!r} is not a seed or a range such as 1000-1199") from None
        if low < 0 or high < low:
            raise ValueError(f"--seeds: {piece!r} is not a range of non-negative seeds, low to high")
        seeds.extend(range(low, high + 1))
    return sorted(set(seeds))


STAGES = ("film", "reconstruct", "field", "inspect", "register")
"""The stages of a scene, each cached on its own (see :func:`stage_keys`)."""
_STAGE_MODULES = {
    "film": ("services.simulation.zoo", "device_gateway.drivers.simulated", "device_gateway.station",
             "services.structured_light.patterns"),
    "reconstruct": ("services.pipeline.reconstruct", "services.pipeline.tables"),
    "field": ("services.pipeline.field",),
    "inspect": ("services.pipeline.inspect", "services.formats.part"),
    "register": ("services.pipeline.register", "services.simulation.thermal", "services.geometry.camera"),
}
_STAGE_INPUT = {"film": None, "reconstruct": "film", "field": "reconstruct", "inspect": "field", "register": "film"}
_PACKAGES = ("services", "device_gateway")


def _module_path(name: str) -> Path | None:
    base = ROOT.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def module_files(names: tuple[str, ...]) -> list[Path]:
    """The repository's source files that importing the modules ``names`` can run: the modules, the packages
    above them, and, transitively, every module of services/ or device_gateway/ that their code imports anywhere
    (also inside functions, which a look at ``sys.modules`` after an import would miss). Read with ``ast``,
    not imported, so that a key costs no import of the code it keys."""
    import ast

    seen: dict[str, Path] = {}
    pending = list(names)
    while pending:
        name = pending.pop()
        parts = name.split(".")
        for depth in range(1, len(parts) + 1):  # a module's packages run on import too
            prefix = ".".join(parts[:depth])
            path = _module_path(prefix)
            if path is None or prefix in seen:
                continue
            seen[prefix] = path
            package = prefix if path.name == "__init__.py" else prefix.rpartition(".")[0]
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                if isinstance(node, ast.Import):
                    found = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom):
                    module = node.module or ""
                    if node.level:
                        anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
                        module = ".".join([*anchor, module] if module else anchor)
                    found = [module] + [f"{module}.{alias.name}" for alias in node.names]
                else:
                    continue
                pending.extend(f for f in found if f.split(".")[0] in _PACKAGES and f not in seen)
    return sorted(set(seen.values()))


def stage_keys() -> dict[str, str]:
    """Per stage, a SHA-256 of the code its result depends on: the source files that its entry modules can
    run (:func:`module_files`), this script's functions for the stage, and the key of the stage whose output it
    takes. Filming depends on the simulator alone, so a change of the structured light, the fusion or the
    inspection re-runs the analysis of the cached frames, not their rendering; a change of the inspection
    re-runs only ``inspect``."""
    import inspect

    functions = {"film": (film_zoo_scene, _film), "reconstruct": (_reconstruct, _interior, _stats),
                 "field": (_field, _stats), "inspect": (_inspect,),
                 "register": (_register, _interior, _best_similarity, registration_truth)}
    keys: dict[str, str] = {}
    for stage in STAGES:
        hasher = hashlib.sha256(f"zoo-{stage}-{RESULT_VERSION}".encode())
        hasher.update((keys.get(_STAGE_INPUT[stage] or "") or "").encode())
        for path in module_files(_STAGE_MODULES[stage]):
            hasher.update(str(path.relative_to(ROOT)).encode())
            hasher.update(path.read_bytes())
        for function in functions[stage]:
            hasher.update(inspect.getsource(function).encode())
        keys[stage] = hasher.hexdigest()
    return keys


def default_cache() -> Path:
    """``$XDG_CACHE_HOME/thermofield/zoo`` (``~/.cache`` by default), beside the triangulation tables."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "thermofield" / "zoo"


def _interior(surface: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """Lit pixels whose 8-neighbours are lit and see the same surface."""
    inside = lit & (surface >= 0)
    inside[[0, -1], :] = False
    inside[:, [0, -1]] = False
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                shifted_surface = np.roll(np.roll(surface, dy, axis=0), dx, axis=1)
                shifted_lit = np.roll(np.roll(lit, dy, axis=0), dx, axis=1)
                inside &= (shifted_surface == surface) & shifted_lit
    return inside


def _stats(values: np.ndarray) -> dict[str, float | None]:
    values = np.asarray(values, dtype=np.float64)
    if len(values) == 0:
        return {"median": None, "p95": None, "max": None}
    finite = np.where(np.isfinite(values), values, 1e9)
    return {"median": float(np.median(finite)), "p95": float(np.percentile(finite, 95)), "max": float(finite.max())}


def _best_similarity(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares similarity (2x3) taking source pixels to target pixels (Umeyama)."""
    import cv2

    matrix, _ = cv2.estimateAffinePartial2D(source.astype(np.float32), target.astype(np.float32), method=cv2.LMEDS)
    return matrix


def film_zoo_scene(zoo, seed: int):
    """Film a zoo scene through the simulated station as the gateway does (auto exposure, one thermal frame):
    the sequence, the capture and the simulated station (its ``view().truth``)."""
    from device_gateway.drivers.simulated import SimulatedStation, SimulationOptions
    from device_gateway.station import ExposureControl, Station
    from services.structured_light.patterns import generate_sequence

    projector = zoo.rig.devices["projector"]
    sequence, patterns = generate_sequence(projector.width, projector.height, closing_black=True)
    options = SimulationOptions(camera_effects=zoo.camera_effects, projector_effects=zoo.projector_effects,
                                thermal_effects=zoo.thermal_effects, camera_supersample=1, seed=seed)
    simulated = SimulatedStation(zoo.rig, zoo.scene, zoo.temperatures, options)
    station = Station(simulated.camera, simulated.thermal, simulated.projector, settle_s=0.0)
    capture = station.capture(sequence, patterns, thermal_frames=1, exposure=ExposureControl(mode="auto"))
    return sequence, capture, simulated


@dataclass(frozen=True)
class Filmed:
    """What filming a zoo scene gives the analysis: the sequence and capture, and the truth of the camera's view
    (per pixel: the surface its centre ray meets, -1 for none; whether the projector lights it; the point)."""

    sequence: object
    frames: np.ndarray
    thermal: np.ndarray
    saturation_level: float
    surface: np.ndarray
    lit: np.ndarray
    points: np.ndarray


def _film(seed: int, zoo) -> tuple[dict, dict]:
    sequence, capture, simulated = film_zoo_scene(zoo, seed)
    truth = simulated.view().truth
    # cached as a dict of the fields: a class of this script pickled in a spawned worker is __mp_main__'s
    return {}, {"sequence": sequence, "frames": np.asarray(capture.frames), "thermal": np.asarray(capture.thermal),
                "saturation_level": capture.exposure["saturation_level"], "surface": truth.surface,
                "lit": truth.lit, "points": truth.points}


def _reconstruct(seed: int, zoo, filmed: Filmed) -> tuple[dict, object]:
    """``thermofield reconstruct`` and the point figures; the cloud (None when refused)."""
    from services.errors import InputError
    from services.pipeline.reconstruct import reconstruct_capture
    from services.pipeline.tables import TriangulationTables

    try:
        reconstruction = reconstruct_capture(frames=filmed.frames, sequence=filmed.sequence, rig=zoo.rig,
                                             tables=TriangulationTables(), saturation_level=filmed.saturation_level)
    except InputError as error:
        return {"refused": str(error), "points": 0, "coverage": 0.0, "part_coverage": 0.0}, None
    interior = _interior(filmed.surface, filmed.lit)
    on_part = filmed.surface == 0
    cloud = reconstruction.cloud
    glow = reconstruction.glow
    u, v = np.rint(cloud["u"]).astype(int), np.rint(cloud["v"]).astype(int)
    points = cloud.points
    error = np.linalg.norm(points - filmed.points[v, u], axis=1)
    error = np.where(np.isfinite(error), error, np.inf)
    has_point = np.zeros(filmed.surface.shape, dtype=bool)
    has_point[v, u] = True
    point_surface = filmed.surface[v, u]
    wrong = error > WRONG_MM
    return {"glow_hint": glow.hint if glow is not None else None,
            "glow_measured": glow.measured_fraction if glow is not None and glow.glowing_fraction else None,
            "points": int(len(points)), "error": _stats(error), "wrong_rate": float(wrong.mean()),
            "wrong": int(wrong.sum()),
            "coverage": float(has_point[interior].mean()) if interior.any() else None,
            "part_coverage": float(has_point[interior & on_part].mean()) if (interior & on_part).any() else None,
            "part_points": int((point_surface == 0).sum()),
            "wrong_on_part": int((wrong & (point_surface == 0)).sum()),
            "wrong_off_part": int((wrong & (point_surface > 0)).sum()),
            "wrong_on_miss": int((wrong & (point_surface < 0)).sum()),
            "wrong_at_edge": int((wrong & ~interior[v, u]).sum()),
            "wrong_in_lit_interior": int((wrong & interior[v, u]).sum()),
            "wrong_unlit": int((wrong & ~filmed.lit[v, u]).sum())}, cloud


def _field(seed: int, zoo, filmed: Filmed, cloud) -> tuple[dict, object]:
    """``thermofield field`` and the temperature figures; the field."""
    from services.pipeline.field import fuse_field

    field = fuse_field(cloud=cloud, rig=zoo.rig, thermal=[(None, filmed.thermal)])
    u, v = np.rint(cloud["u"]).astype(int), np.rint(cloud["v"]).astype(int)
    point_surface = filmed.surface[v, u]
    temperature = np.asarray(field["temperature"], dtype=np.float64)
    part_index = np.flatnonzero(point_surface == 0)
    true_temperature = zoo.temperatures.surfaces[0].evaluate(filmed.points[v[part_index], u[part_index]])
    measured = temperature[part_index]
    has_temperature = np.isfinite(measured)
    temperature_error = np.abs(measured[has_temperature] - true_temperature[has_temperature])
    off_part = np.isfinite(temperature) & (point_surface != 0)
    return {"part_with_temperature": float(has_temperature.mean()) if len(part_index) else None,
            "temperature_error": _stats(temperature_error),
            "temperature_off_20k": float((temperature_error > 20.0).mean()) if len(temperature_error) else None,
            "hot_readings_off_part": int((temperature[off_part] >= 300.0).sum())}, field


def _inspect(seed: int, zoo, field) -> tuple[dict, None]:
    """``thermofield inspect`` with the scene's part file: the verdict, surface and features against the truth."""
    from services.errors import InputError
    from services.formats.part import load_part
    from services.pipeline.inspect import inspect_part, prepare_part_type

    with tempfile.TemporaryDirectory(prefix="zoo-part-") as directory:
        part = load_part(zoo.write_part(directory))
        try:
            outcome = inspect_part(field=field, part=prepare_part_type(part))
        except InputError as error:
            return {"verdict": "refused", "inspect_error": str(error)}, None
    report = outcome.report
    result: dict = {"verdict": report["verdict"],
                    "surface": {key: report["surface"].get(key) for key in ("cell_min", "cell_max", "uncertainty",
                                                                            "verdict")}}
    features = {}
    for feature in report["features"]:
        entry = {key: feature.get(key) for key in ("verdict", "cold", "uncertainty", "error")}
        if feature["name"] in zoo.truth.features and feature.get("cold") is not None:
            entry["cold_error"] = float(feature["cold"]) - zoo.truth.features[feature["name"]]
        features[feature["name"]] = entry
    result["features"] = features
    return result, None


def _register(seed: int, zoo, filmed: Filmed) -> tuple[dict, None]:
    """``thermofield register`` of the thermal frame onto the white frame, against the true correspondences."""
    from services.errors import InputError
    from services.pipeline.register import register_pair, white_frame
    from services.simulation.thermal import seen_by

    thermal = zoo.rig.devices["thermal"]
    visible = white_frame(filmed.frames, filmed.sequence).astype(np.float32)
    infrared = np.nan_to_num(filmed.thermal[0].astype(np.float32), nan=float(np.nanmin(filmed.thermal[0])))
    try:
        registration = register_pair(fixed=visible, moving=infrared, source=f"zoo scene {seed}")
    except InputError as error:
        return {"register_error": str(error)}, None
    result: dict = {}
    rows, columns = np.nonzero(_interior(filmed.surface, filmed.lit) & (filmed.surface == 0))
    pick = np.random.default_rng(seed).permutation(len(rows))[:4000]
    world = filmed.points[rows[pick], columns[pick]]
    seen = seen_by(zoo.scene, thermal, world)
    thermal_pixels = thermal.project(world[seen])
    inside = ((thermal_pixels[:, 0] >= 0) & (thermal_pixels[:, 0] <= thermal.width - 1)
              & (thermal_pixels[:, 1] >= 0) & (thermal_pixels[:, 1] <= thermal.height - 1))
    visible_pixels = np.column_stack([columns[pick], rows[pick]])[seen][inside].astype(np.float64)
    thermal_pixels = thermal_pixels[inside]
    if len(thermal_pixels) >= 10:
        matrix = np.asarray(registration.matrix, dtype=np.float64)[:2]
        mapped = thermal_pixels @ matrix[:, :2].T + matrix[:, 2]
        best = _best_similarity(thermal_pixels, visible_pixels)
        fitted = thermal_pixels @ best[:, :2].T + best[:, 2]
        result["register_px"] = float(np.median(np.linalg.norm(mapped - visible_pixels, axis=1)))
        result["register_truth"] = registration_truth(zoo)
        result["register_best_px"] = float(np.median(np.linalg.norm(fitted - visible_pixels, axis=1)))
    return result, None


def _stage(name: str, seed: int, cache: Path, keys: dict[str, str], compute) -> tuple[dict, object]:
    """``compute()`` -> (figures, output), read from or written to ``cache/name/seed-key.pkl``; the figures
    get ``name_s``, the seconds the computation took (those of the run that filled the cache)."""
    from services.geometry.cloud import PointCloud

    path = cache / name / f"{seed}-{keys[name][:16]}.pkl"
    if path.is_file():
        with path.open("rb") as file:
            figures, output = pickle.load(file)
        if isinstance(output, tuple) and output[:1] == ("PointCloud",):
            output = PointCloud(*output[1:])
        return figures, output
    started = time.perf_counter()
    figures, output = compute()
    figures = {**figures, f"{name}_s": round(time.perf_counter() - started, 1)}
    stored = output
    if isinstance(output, PointCloud):  # its read-only mappings do not pickle: its arrays do
        stored = ("PointCloud", dict(output.properties), dict(output.units), output.comments)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(f".{os.getpid()}.tmp")
    with temporary.open("wb") as file:
        pickle.dump((figures, stored), file, protocol=pickle.HIGHEST_PROTOCOL)
    temporary.replace(path)
    return figures, output


def run_scene(seed: int, cache: Path, keys: dict[str, str], stages: tuple[str, ...] = STAGES) -> dict:
    """Film scene ``seed``, run the commands' use cases and score them against the truth, each stage read from
    ``cache`` when its key's result is there (``stages``: those to run, with the stages they take output from)."""
    zoo = zoo_scene(seed)
    result: dict = {"seed": seed, "kind": zoo.kind, "in_tolerance": zoo.truth.in_tolerance,
                    "truth": zoo.truth.deviation, "scene": zoo.description}
    figures, filmed = _stage("film", seed, cache, keys, lambda: _film(seed, zoo))
    filmed = Filmed(**filmed)
    result.update(figures)
    if "register" in stages:
        result.update(_stage("register", seed, cache, keys, lambda: _register(seed, zoo, filmed))[0])
    if not {"reconstruct", "field", "inspect"} & set(stages):
        return _seconds(result)
    figures, cloud = _stage("reconstruct", seed, cache, keys, lambda: _reconstruct(seed, zoo, filmed))
    result.update(figures)
    if cloud is None or not {"field", "inspect"} & set(stages):
        return _seconds(result)
    figures, field = _stage("field", seed, cache, keys, lambda: _field(seed, zoo, filmed, cloud))
    result.update(figures)
    if "inspect" in stages:
        result.update(_stage("inspect", seed, cache, keys, lambda: _inspect(seed, zoo, field))[0])
    return _seconds(result)


def _seconds(result: dict) -> dict:
    """``seconds``: what the scene's stages cost together when computed (not reading the cache)."""
    result["seconds"] = round(sum(result.get(f"{stage}_s", 0.0) for stage in STAGES), 1)
    return result


def registration_truth(zoo) -> dict[str, float]:
    """The similarity that best takes the part's thermal pixels to its visible pixels (from the geometry, no
    rendering) and where it lies against ``thermofield register``'s default search range: its scale relative
    to the nominal scale (the moving image fitted inside the fixed one; searched within +-12 %), its angle
    (+-6 degrees) and the shift of the thermal image's centre from the fitted-inside placement, as a share of
    the thermal image's width (12 %)."""
    import cv2

    camera, thermal = zoo.rig.devices["camera"], zoo.rig.devices["thermal"]
    points = np.asarray(zoo.scene.surfaces[0].vertices)[::7]
    visible = camera.project(points)
    infrared = thermal.project(points)
    matrix, _ = cv2.estimateAffinePartial2D(infrared.astype(np.float32), visible.astype(np.float32))
    scale = float(np.hypot(matrix[0, 0], matrix[1, 0]))
    nominal = min(camera.width / thermal.width, camera.height / thermal.height)
    centre = matrix[:, :2] @ [(thermal.width - 1) / 2, (thermal.height - 1) / 2] + matrix[:, 2]
    shift = np.linalg.norm(centre - [(camera.width - 1) / 2, (camera.height - 1) / 2])
    return {"scale_change": scale / nominal - 1, "angle_deg": float(np.degrees(np.arctan2(matrix[1, 0], matrix[0, 0]))),
            "shift_fraction": float(shift / nominal / thermal.width)}


def within_search_range(truth: dict[str, float]) -> bool:
    """Whether the true similarity lies inside ``register``'s default search range."""
    return abs(truth["scale_change"]) <= 0.12 and abs(truth["angle_deg"]) <= 6.0 and truth["shift_fraction"] <= 0.12


def _guarded_run(seed: int, cache: Path, keys: dict[str, str], stages: tuple[str, ...]) -> dict:
    try:
        return run_scene(seed, cache, keys, stages)
    except Exception:  # a crash is a finding: record it and go on with the other scenes
        return {"seed": seed, "crash": traceback.format_exc(limit=6)}


def _percentile(values: list[float], q: float) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.percentile(values, q)) if values else None


def _fmt(value: float | None, scale: float = 1.0, digits: int = 3, unit: str = "") -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}{unit}"


def summarise(results: list[dict], command: str, tuning: bool) -> str:
    """The markdown tables of docs/zoo.md."""
    crashed = [r for r in results if "crash" in r]
    done = [r for r in results if "crash" not in r]
    refused = [r for r in done if "refused" in r]
    scored = [r for r in done if "refused" not in r]
    seeds = sorted(r["seed"] for r in results)
    lines = [f"Command: `{command}`", "",
             f"Data: zoo {'TUNING (not held out)' if tuning else 'held-out reporting'} seeds "
             f"{seeds[0]}..{seeds[-1]}, {len(results)} scenes ({len(scored)} reconstructed, {len(refused)} refused "
             f"by reconstruct, {len(crashed)} crashed).", ""]

    def row(name: str, values: list[float | None], scale: float = 1.0, digits: int = 3, unit: str = "") -> str:
        return (f"| {name} | {_fmt(_percentile(values, 50), scale, digits, unit)} | "
                f"{_fmt(_percentile(values, 95), scale, digits, unit)} | "
                f"{_fmt(_percentile(values, 5), scale, digits, unit)} | "
                f"{_fmt(max((v for v in values if v is not None), default=None), scale, digits, unit)} |")

    lines += ["| per scene | median scene | 95th percentile scene | 5th percentile scene | worst scene |",
              "|---|---|---|---|---|",
              row("points more than 1 mm off", [r["wrong_rate"] for r in scored], 100, 3, " %"),
              row("point error, median (mm)", [r["error"]["median"] for r in scored], 1, 4),
              row("point error, 95th percentile (mm)", [r["error"]["p95"] for r in scored], 1, 4),
              row("point error, worst (mm)", [r["error"]["max"] for r in scored], 1, 2),
              row("coverage of the lit, seen surface", [r["coverage"] for r in scored], 100, 1, " %"),
              row("coverage of the part", [r["part_coverage"] for r in scored], 100, 1, " %"),
              row("part points with a temperature", [r.get("part_with_temperature") for r in scored], 100, 1, " %"),
              row("temperature error, median (K)", [r["temperature_error"]["median"] for r in scored], 1, 2),
              row("temperature error, 95th percentile (K)", [r["temperature_error"]["p95"] for r in scored], 1, 1),
              row("part points > 20 K off", [r.get("temperature_off_20k") for r in scored], 100, 2, " %"),
              row("registration, median px (visible)", [r.get("register_px") for r in scored], 1, 2),
              row("best similarity, median px (visible)", [r.get("register_best_px") for r in scored], 1, 2),
              row("seconds per scene", [r.get("seconds") for r in scored], 1, 0), ""]
    inside = [r for r in scored if r.get("register_truth") and within_search_range(r["register_truth"])]
    if any(r.get("register_truth") for r in scored):
        lines += [f"Registration: the true thermal-to-visible similarity lies inside `register`'s default search range "
                  f"(scale +-12 % of the fitted-inside scale, +-6 degrees, shift 12 %) in {len(inside)} of "
                  f"{len(scored)} scenes; on those the median scene's registration is off by "
                  f"{_fmt(_percentile([r.get('register_px') for r in inside], 50), 1, 1)} px (best similarity "
                  f"{_fmt(_percentile([r.get('register_best_px') for r in inside], 50), 1, 1)} px).", ""]
    cold = [abs(f["cold_error"]) for r in scored for f in r.get("features", {}).values() if "cold_error" in f]
    lines += [f"Cold size error (diameter, or a box's length), |cold - true|, over {len(cold)} features: median "
              f"{_fmt(_percentile(cold, 50), 1, 3)} mm, 95th percentile {_fmt(_percentile(cold, 95), 1, 3)} mm, "
              f"worst {_fmt(max(cold, default=None), 1, 3)} mm.", ""]
    verdicts = ("OK", "NotOK", "NotDecidable", "refused")
    lines += ["| truth \\ verdict | " + " | ".join(verdicts) + " |", "|---|" + "---|" * len(verdicts)]
    for truth, label in ((True, "in tolerance"), (False, "out of tolerance")):
        group = [r for r in done if r["in_tolerance"] == truth]
        counts = [sum(1 for r in group if r.get("verdict", "refused") == verdict) for verdict in verdicts]
        lines.append(f"| {label} ({len(group)}) | " + " | ".join(map(str, counts)) + " |")
    lines.append("")
    kinds = sorted({r["kind"] for r in done})
    lines += ["| part kind | scenes | wrong > 1 mm, median scene | worst scene | part coverage, median | "
              "in tol. OK | out of tol. NotOK |", "|---|---|---|---|---|---|---|"]
    for kind in kinds:
        group = [r for r in scored if r["kind"] == kind]
        inside = [r for r in group if r["in_tolerance"]]
        outside = [r for r in group if not r["in_tolerance"]]
        lines.append(f"| {kind} | {len(group)} | {_fmt(_percentile([r['wrong_rate'] for r in group], 50), 100, 3, ' %')} | "
                     f"{_fmt(max((r['wrong_rate'] for r in group), default=None), 100, 3, ' %')} | "
                     f"{_fmt(_percentile([r['part_coverage'] for r in group], 50), 100, 1, ' %')} | "
                     f"{sum(r.get('verdict') == 'OK' for r in inside)}/{len(inside)} | "
                     f"{sum(r.get('verdict') == 'NotOK' for r in outside)}/{len(outside)} |")
    lines.append("")
    for light in ("blue", "white"):
        group = [r for r in scored if r["scene"]["light"] == light]
        if group:
            lines.append(f"- {light} projector ({len(group)} scenes): wrong > 1 mm median scene "
                         f"{_fmt(_percentile([r['wrong_rate'] for r in group], 50), 100, 3, ' %')}, 95th percentile "
                         f"{_fmt(_percentile([r['wrong_rate'] for r in group], 95), 100, 3, ' %')}; part coverage median "
                         f"{_fmt(_percentile([r['part_coverage'] for r in group], 50), 100, 1, ' %')}.")
    lines += ["", *failure_classes(done)]
    if refused:
        lines.append(f"- refused by reconstruct: seeds {', '.join(str(r['seed']) for r in refused)}.")
    if crashed:
        lines.append(f"- crashed: seeds {', '.join(str(r['seed']) for r in crashed)} (traceback in the JSON).")
    return "\n".join(lines) + "\n"


def _seeds(group: list[dict]) -> str:
    return ", ".join(str(r["seed"]) for r in group) or "none"


def undecided_reason(result: dict) -> str:
    """Why a NotDecidable verdict came, against the truth: ``"limit"`` where an item judged NotDecidable has its
    true value within its expanded uncertainty of a tolerance limit (what the issue allows), ``"covered"`` where
    none has but each such item's uncertainty covers its error (the measurement, within its stated uncertainty,
    put a limit within reach), ``"error"`` where an item's error exceeds its uncertainty (a measurement error,
    I5), ``"unknown"`` where no undecided item has a known truth.

    A feature's truth is the zoo's true cold value (left out where a dent or bulge changes what it measures);
    the surface's true extremes are the drawn dent or bulge and half of each feature's true size offset (the
    surface of a diameter off by d lies d/2 off), against the part file's surface tolerance and the report's
    cell extremes.
    """
    zoo = zoo_scene(result["seed"])
    found: list[tuple[bool, bool]] = []  # per undecided item: (true value within U of a limit, U covers the error)
    for feature in zoo.part_file["features"]:
        entry = result.get("features", {}).get(feature["name"], {})
        true = zoo.truth.features.get(feature["name"])
        if entry.get("verdict") == "NotDecidable" and true is not None and entry.get("uncertainty") is not None:
            low, high = (feature["nominal"] + limit for limit in feature["tolerance"])
            u = entry["uncertainty"]
            found.append((min(abs(true - low), abs(true - high)) <= u, abs(entry["cold"] - true) <= u))
    surface = result.get("surface") or {}
    if surface.get("verdict") == "NotDecidable" and surface.get("uncertainty") is not None:
        offsets = [bump.height_mm for bump in zoo.part.bumps]
        offsets += [(zoo.truth.features[f["name"]] - f["nominal"]) / 2 for f in zoo.part_file["features"]
                    if f["name"] in zoo.truth.features]
        upper, lower = max([0.0, *offsets]), min([0.0, *offsets])
        low, high = zoo.part_file["surface_tolerance"]
        u = surface["uncertainty"]
        found.append((min(high - upper, lower - low) <= u,
                      surface["cell_max"] - upper <= u and lower - surface["cell_min"] <= u))
    if not found:
        return "unknown"
    if any(within for within, _ in found):
        return "limit"
    return "covered" if all(covered for _, covered in found) else "error"


def failure_classes(results: list[dict]) -> list[str]:
    """Where the wrong points lie and which scenes each wrong verdict comes from (markdown lines)."""
    scored = [r for r in results if "refused" not in r]
    total = sum(r["wrong"] for r in scored) or 1
    lines = ["Where the points more than 1 mm off lie (all scenes together; a point may be in several rows):", "",
             "| where | points | share of the wrong points |", "|---|---|---|"]
    for key, label in (("wrong_at_edge", "at a depth edge (a pixel whose 8-neighbours see another surface or are unlit)"),
                       ("wrong_unlit", "on a pixel the projector does not light (shadow or facing away)"),
                       ("wrong_in_lit_interior", "inside a lit surface, away from edges"),
                       ("wrong_on_part", "on the part"), ("wrong_off_part", "on fixtures and the wall"),
                       ("wrong_on_miss", "where the pixel's centre ray meets nothing")):
        count = sum(r.get(key, 0) for r in scored)
        lines.append(f"| {label} | {count} | {100 * count / total:.1f} % |")
    lines.append("")
    false_not_ok = [r for r in results if r["in_tolerance"] and r.get("verdict") == "NotOK"]
    false_ok = [r for r in results if not r["in_tolerance"] and r.get("verdict") == "OK"]
    undecided = [r for r in results if r.get("verdict") == "NotDecidable"]
    reasons = {r["seed"]: undecided_reason(r) for r in undecided}
    because = {reason: [r for r in undecided if reasons[r["seed"]] == reason]
               for reason in ("limit", "covered", "error", "unknown")}
    refused = [r for r in results if r.get("verdict") == "refused"]
    unseen = [r for r in results if (r.get("part_points") or 0) < 100 and r.get("verdict") in ("OK", "NotOK")]
    far = [r for r in false_not_ok if r.get("surface") and r["surface"].get("cell_min") is not None
           and max(abs(r["surface"]["cell_min"]), abs(r["surface"]["cell_max"])) > 4.0]
    size_wrong = [r for r in false_not_ok if any(f.get("verdict") == "NotOK" for f in r.get("features", {}).values())]
    lines += [f"- false NotOK (in tolerance, rejected): {len(false_not_ok)}: seeds {_seeds(false_not_ok)}; of them "
              f"{len(far)} with a surface cell beyond 4 mm (near the 5 mm segmentation distance: alignment or "
              f"segmentation, not a dent): {_seeds(far)}; {len(size_wrong)} with a size feature NotOK: "
              f"{_seeds(size_wrong)}.",
              f"- false OK (out of tolerance, passed): {len(false_ok)}: seeds {_seeds(false_ok)}.",
              f"- NotDecidable: {len(undecided)}: seeds {_seeds(undecided)}; of them, against the truth: "
              f"{len(because['limit'])} with a true value within the expanded uncertainty of a limit (what the "
              f"issue allows): {_seeds(because['limit'])}; {len(because['covered'])} with the true value further, "
              f"the uncertainty covering the error: {_seeds(because['covered'])}; {len(because['error'])} with an "
              f"error beyond the uncertainty (I5): {_seeds(because['error'])}; {len(because['unknown'])} with no "
              f"known truth for the undecided item: {_seeds(because['unknown'])}.",
              f"- inspect refused (an error): {len(refused)}: seeds {_seeds(refused)}.",
              f"- a verdict on a part with fewer than 100 reconstructed points: {len(unseen)}: seeds {_seeds(unseen)}."]
    hot_off = [r for r in scored if r.get("hot_readings_off_part", 0) >= 100]
    lines.append(f"- 100 or more fixture or wall points given a part temperature (>= 300 C) by the field: "
                 f"{len(hot_off)}: seeds {_seeds(hot_off)}.")
    return lines


def write_markdown(path: Path, table: str) -> None:
    """Put ``table`` between the zoo-table markers of ``path`` (the whole file when it has none)."""
    block = f"{_BEGIN}\n{table}{_END}\n"
    if path.is_file() and _BEGIN in (text := path.read_text()) and _END in text:
        head, rest = text.split(_BEGIN, 1)
        path.write_text(head + block + rest.split(_END, 1)[1].lstrip("\n"))
    else:
        path.write_text("# The scene zoo\n\n" + block)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Run the real commands over zoo scenes and report distributions (docs/zoo.md).",
        epilog=f"Tuning seeds {TUNING_SEEDS.start}..{TUNING_SEEDS.stop - 1} may be used to choose thresholds and "
               f"are never reported; reporting seeds {REPORTING_SEEDS.start}..{REPORTING_SEEDS.stop - 1} are held "
               "out (at least 200 scenes for the issue's targets).",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default=f"{REPORTING_SEEDS.start}-{REPORTING_SEEDS.stop - 1}",
                        help="seeds and ranges, e.g. 1000-1199 (default: the reporting seeds)")
    parser.add_argument("--jobs", type=int, default=1, help="scenes run in parallel processes")
    parser.add_argument("--json", type=Path, required=True, help="per-scene results (JSON) are written here")
    parser.add_argument("--markdown", type=Path, default=None, help="write the tables into this file (docs/zoo.md)")
    parser.add_argument("--cache", type=Path, default=default_cache(),
                        help="per-stage cache of the scenes (default $XDG_CACHE_HOME/thermofield/zoo)")
    parser.add_argument("--allow-tuning", action="store_true", help="allow tuning seeds into --markdown")
    parser.add_argument("--summarise", action="store_true",
                        help="run nothing: read the per-scene results of --json (those of --seeds) and write the tables")
    parser.add_argument("--stages", default=",".join(STAGES),
                        help=f"the stages to run (and those whose output they take), of {', '.join(STAGES)}; the "
                             "tables need all of them (e.g. --stages film to render scenes into the cache alone)")
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as error:
        parser.error(str(error))
    stages = tuple(stage.strip() for stage in args.stages.split(",") if stage.strip())
    if unknown := [stage for stage in stages if stage not in STAGES]:
        parser.error(f"--stages: {', '.join(unknown)} is not a stage; the stages are {', '.join(STAGES)}")
    if set(stages) != set(STAGES) and (args.markdown is not None or args.summarise):
        parser.error("--stages: the tables (--markdown, --summarise) need every stage")
    if not seeds:
        parser.error("--seeds names no seed")
    if args.jobs < 1:
        parser.error("--jobs must be at least 1")
    tuning = any(seed in TUNING_SEEDS for seed in seeds)
    if tuning and args.markdown is not None and not args.allow_tuning:
        parser.error(f"--seeds includes tuning seeds ({TUNING_SEEDS.start}..{TUNING_SEEDS.stop - 1}); they are never "
                     "reported (give --allow-tuning to write them anyway, marked as such)")
    results: list[dict] = []

    def keep(result: dict) -> None:  # the JSON is rewritten after every scene, so a cut-short run keeps its scenes
        results.append(result)
        results.sort(key=lambda r: r["seed"])
        args.json.write_text(json.dumps(results, indent=1, default=float))
        print(json.dumps({k: result.get(k) for k in ("seed", "kind", "wrong_rate", "coverage", "verdict",
                                                     "in_tolerance", "seconds")}), flush=True)

    if args.summarise:
        wanted = set(seeds)
        results = [r for r in json.loads(args.json.read_text()) if r["seed"] in wanted]
        if not results:
            parser.error(f"--summarise: {args.json} holds none of the seeds asked for")
        for result in results:  # results of an earlier version lack it: the geometry gives it without rendering
            if "register_px" in result and "register_truth" not in result:
                result["register_truth"] = registration_truth(zoo_scene(result["seed"]))
        args.json.write_text(json.dumps(results, indent=1, default=float))
    else:
        keys = stage_keys()
        args.json.parent.mkdir(parents=True, exist_ok=True)
        if args.jobs == 1:
            for seed in seeds:
                keep(_guarded_run(seed, args.cache, keys, stages))
        else:
            # spawned, not forked: a process that has used OpenMP (numba, Open3D) cannot fork safely
            with ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
                futures = [pool.submit(_guarded_run, seed, args.cache, keys, stages) for seed in seeds]
                for future in as_completed(futures):
                    keep(future.result())
    if set(stages) != set(STAGES):
        return 0
    command = "python experiments/zoo.py " + " ".join(argv if argv is not None else sys.argv[1:])
    table = summarise(results, command, tuning)
    print(table)
    if args.markdown is not None:
        write_markdown(args.markdown, table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
