"""The segmentation's normals' rule (issue 34; docs/inspection.md, "Which points near the nominal are the
part's"): its CPU cost and its angle, on zoo scenes' cached fields.

Run (fields from experiments/zoo.py's cache: film them first with --stages film,reconstruct,field):

    nice -n 10 .venv/bin/python experiments/zoo_segmentation.py cpu --seeds 0-99 --json cpu.json
    nice -n 10 .venv/bin/python experiments/zoo_segmentation.py angles --seeds 0-99 --json angles.json

``cpu``: per scene, ``inspect_field``'s process CPU seconds with the rule and without it (the rule replaced by
one that keeps every point within the segmentation distance: the segmentation as it was before), the same
field and prepared part one after the other, the order alternating with the seed; the distance grid is built
before the timing. ``angles``: the zoo's own ``inspect`` stage with the rule's bound at 45, 60 and 75 degrees:
per angle the verdict, the extreme surface cells and the report's ``segmentation`` block.
"""

from __future__ import annotations

import functools
import glob
import json
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import zoo as zoo_script  # noqa: E402

import services.inspection.inspect as inspect_module  # noqa: E402
import services.pipeline.inspect as pipeline_inspect  # noqa: E402
from services.formats.part import load_part  # noqa: E402
from services.geometry.cloud import PointCloud  # noqa: E402
from services.simulation.zoo import zoo_scene  # noqa: E402

_RULE = inspect_module.agrees_with_nominal


def _every_point(points_part, normals_part, nominal, *args, **kwargs):
    """The segmentation before the rule: every point within the distance is the part's."""
    return np.ones(len(points_part), dtype=bool)


def _field(seed: int, cache: Path):
    paths = glob.glob(str(cache / "field" / f"{seed}-*.pkl"))
    if not paths:
        return None
    with open(paths[0], "rb") as file:
        _, stored = pickle.load(file)
    return PointCloud(*stored[1:]) if isinstance(stored, tuple) else stored


def _scenes(seeds: list[int], cache: Path):
    """Each seed with a cached field: (seed, its zoo scene, the field)."""
    for seed in seeds:
        field = _field(seed, cache)
        if field is not None:
            yield seed, zoo_scene(seed), field


def cpu(seeds: list[int], cache: Path) -> list[dict]:
    rows = []
    for seed, zoo, field in _scenes(seeds, cache):
        with tempfile.TemporaryDirectory(prefix="zoo-part-") as directory:
            part = load_part(zoo.write_part(directory))
        prepared = inspect_module.prepare_part(part)
        prepared.nominal.signed_distance(prepared.nominal.samples[:1])  # the distance grid, outside the timing
        properties = dict(field.items())
        seconds = {}
        for rule in ((True, False) if seed % 2 else (False, True)):
            inspect_module.agrees_with_nominal = _RULE if rule else _every_point
            started = time.process_time()
            try:
                inspect_module.inspect_field(field=properties, part=prepared)
            except ValueError:
                pass
            seconds[rule] = time.process_time() - started
        inspect_module.agrees_with_nominal = _RULE
        rows.append({"seed": seed, "with": seconds[True], "without": seconds[False],
                     "ratio": seconds[True] / seconds[False]})
        print(json.dumps(rows[-1]), flush=True)
    ratio = np.array([row["ratio"] for row in rows])
    if len(ratio):
        print(json.dumps({"scenes": len(ratio), "median_ratio": float(np.median(ratio)),
                          "p95_ratio": float(np.percentile(ratio, 95)), "worst_ratio": float(ratio.max()),
                          "total_ratio": sum(row["with"] for row in rows) / sum(row["without"] for row in rows)}))
    return rows


def angles(seeds: list[int], cache: Path, bounds: tuple[float, ...] = (45.0, 60.0, 75.0)) -> list[dict]:
    captured: dict = {}

    def capturing(*, field, part, _inspect=inspect_module.inspect_field):
        result = _inspect(field=field, part=part)
        captured["segmentation"] = result.report["segmentation"]
        return result

    pipeline_inspect.inspect_field = capturing
    rows = []
    for seed, zoo, field in _scenes(seeds, cache):
        row = {"seed": seed, "kind": zoo.kind, "in_tolerance": zoo.truth.in_tolerance}
        for bound in bounds:
            inspect_module.agrees_with_nominal = functools.partial(_RULE, max_angle_deg=bound)
            captured.clear()
            result, _ = zoo_script._inspect(seed, zoo, field)
            surface = result.get("surface") or {}
            row[f"{bound:g}"] = {"verdict": result["verdict"], "cell_min": surface.get("cell_min"),
                                 "cell_max": surface.get("cell_max"), "segmentation": captured.get("segmentation")}
        inspect_module.agrees_with_nominal = _RULE
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = zoo_script.cached_scene_parser(__doc__.splitlines()[0], ("cpu", "angles"))
    args = parser.parse_args(argv)
    seeds = zoo_script.parse_seeds(args.seeds)
    cache = args.cache or zoo_script.default_cache()
    rows = cpu(seeds, cache) if args.mode == "cpu" else angles(seeds, cache)
    args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
