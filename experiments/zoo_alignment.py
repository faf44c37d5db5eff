"""The alignment with and without the field's normals (issue 34, I1): zoo scenes inspected both ways, and
constructed one-sided views of zoo parts aligned.

Run (docs/zoo.md, I1):

    # filmed scenes: fields from experiments/zoo.py's cache (film them first with --stages film,reconstruct,field)
    nice -n 10 .venv/bin/python experiments/zoo_alignment.py fields --seeds 1000-1009 --json out.json
    # constructed views: the nominal's samples that the scene's camera and projector both see (no fixtures,
    # no filming), 0.03 mm noise on the points, N(0, 0.15) on each normal's components, then renormalised
    nice -n 10 .venv/bin/python experiments/zoo_alignment.py views --seeds 0-99 --json out.json [--without-normals]

``fields``: each scene's cached field goes through the zoo's own ``inspect`` stage twice in one process,
with its ``nx, ny, nz`` and without them (which is the alignment as it was before them), in alternating
order; per run the verdict, the surface's extreme cells, the cold-size errors, the pose error (95th
percentile over the nominal's samples of the distance between the nominal placed by the alignment and
by the truth; symmetric poses count as right) and the process CPU seconds spent in ``align_nominal``.
``views``: the pose error (worst sample) and the coarse alignment's CPU seconds.
"""

from __future__ import annotations

import glob
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import zoo as zoo_script  # noqa: E402

import services.inspection.inspect as inspect_module  # noqa: E402
import services.pipeline.inspect as pipeline_inspect  # noqa: E402
from services.geometry.cloud import PointCloud  # noqa: E402
from services.inspection.alignment import align_nominal  # noqa: E402
from services.inspection.nominal import NominalSurface  # noqa: E402
from services.simulation.raycast import cast_rays  # noqa: E402
from services.simulation.scene import Mesh, Scene  # noqa: E402
from services.simulation.zoo import zoo_scene  # noqa: E402

_clock = {"s": 0.0}
_captured: dict = {}


def _timed_align(*args, **kwargs):
    started = time.process_time()
    try:
        return align_nominal(*args, **kwargs)
    finally:
        _clock["s"] += time.process_time() - started


def _capturing_inspect(*, field, part, _inspect=inspect_module.inspect_field):
    result = _inspect(field=field, part=part)
    _captured["matrix"], _captured["nominal"] = result.alignment.matrix, part.nominal
    return result


def _pose_errors(nominal: NominalSurface, found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    world = nominal.samples @ found[:3, :3].T + found[:3, 3]
    return np.abs(nominal.signed_distance((world - truth[:3, 3]) @ truth[:3, :3]))


def _inspected(seed: int, zoo, field: PointCloud, with_normals: bool) -> dict:
    if not with_normals:
        field = field.without("nx", "ny", "nz")
    _clock["s"] = 0.0
    _captured.clear()
    started = time.process_time()
    result, _ = zoo_script._inspect(seed, zoo, field)
    out = {"verdict": result["verdict"], "align_s": _clock["s"], "inspect_s": time.process_time() - started,
           "cell_max": (result.get("surface") or {}).get("cell_max"),
           "cell_min": (result.get("surface") or {}).get("cell_min"),
           "cold_error": {name: f.get("cold_error") for name, f in (result.get("features") or {}).items()}}
    if "matrix" in _captured:
        out["pose_err95"] = float(np.percentile(_pose_errors(_captured["nominal"], _captured["matrix"],
                                                             zoo.part.pose), 95))
    return out


def fields(seeds: list[int], cache: Path) -> list[dict]:
    # the alignment's time and the aligned pose, read in the use case that the zoo's inspect stage runs
    inspect_module.align_nominal = _timed_align
    pipeline_inspect.inspect_field = _capturing_inspect
    rows = []
    for seed in seeds:
        paths = glob.glob(str(cache / "field" / f"{seed}-*.pkl"))
        if not paths:
            print(json.dumps({"seed": seed, "missing": "no cached field"}), flush=True)
            continue
        with open(paths[0], "rb") as file:
            _, stored = pickle.load(file)
        field = PointCloud(*stored[1:]) if isinstance(stored, tuple) else stored
        zoo = zoo_scene(seed)
        row = {"seed": seed, "kind": zoo.kind, "in_tolerance": zoo.truth.in_tolerance}
        for with_normals in ((False, True) if seed % 2 else (True, False)):
            row["after" if with_normals else "before"] = _inspected(seed, zoo, field, with_normals)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def _seen(nominal: NominalSurface, pose: np.ndarray, viewers: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    world = nominal.samples @ pose[:3, :3].T + pose[:3, 3]
    normals = nominal.sample_normals @ pose[:3, :3].T
    scene = Scene(surfaces=[Mesh(vertices=(nominal.vertices @ pose[:3, :3].T + pose[:3, 3]).tolist(),
                                 faces=nominal.triangles.tolist())])
    keep = np.ones(len(world), dtype=bool)
    for viewer in viewers:
        toward = world - viewer
        distance = np.linalg.norm(toward, axis=1)
        facing = np.einsum("ij,ij->i", normals, toward) < -0.2 * distance
        first = np.zeros(len(world), dtype=bool)
        first[np.flatnonzero(facing)] = cast_rays(scene, viewer, toward[facing]).distance > distance[facing] - 1e-3
        keep &= first
    return world[keep], normals[keep]


def views(seeds: list[int], with_normals: bool) -> list[dict]:
    rows = []
    for seed in seeds:
        zoo = zoo_scene(seed)
        nominal = NominalSurface(zoo.nominal_vertices, zoo.nominal_triangles)
        devices = zoo.rig.devices
        points, normals = _seen(nominal, zoo.part.pose, [devices["camera"].centre, devices["projector"].centre])
        rng = np.random.default_rng(seed)
        points = points + rng.normal(0, 0.03, points.shape)
        normals = normals + rng.normal(0, 0.15, normals.shape)
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True) if with_normals else None
        nominal.signed_distance(nominal.samples[:1])  # the distance grid, built outside the timing
        started = time.process_time()
        coarse = align_nominal(points, nominal, max_distance_mm=5.0, polish=False, normals=normals)
        seconds = time.process_time() - started
        final = align_nominal(points, nominal, max_distance_mm=5.0, start=coarse.matrix, normals=normals)
        row = {"seed": seed, "kind": zoo.kind, "points": len(points),
               "pose_err": float(_pose_errors(nominal, final.matrix, zoo.part.pose).max()),
               "rms": final.rms_mm, "inlier_fraction": final.inlier_fraction, "coarse_s": seconds}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = zoo_script.cached_scene_parser(__doc__.splitlines()[0], ("fields", "views"))
    parser.add_argument("--without-normals", action="store_true", help="views: align without the normals")
    args = parser.parse_args(argv)
    seeds = zoo_script.parse_seeds(args.seeds)
    if args.mode == "fields":
        rows = fields(seeds, args.cache or zoo_script.default_cache())
    else:
        rows = views(seeds, not args.without_normals)
    args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
