"""The example part type of the simulated station: the cold nominal of ``presets.forging_scene()``'s forging.

The simulated forging is a capped billet (radius 55 mm, length 220 mm, about 1040 degC) with a coaxial
flange (radius 80 mm, length 24 mm, about 960 degC), as hot as the gateway's simulator renders it. Its
cold nominal is that shape shrunk by each body's thermal strain (EN 1993-1-2 carbon steel), in the part's
own frame: the billet's axis along x, its centre at the origin. ``thermofield demo`` uploads it as a part
type, so that its scan ends with a verdict; the files ship in ``services/simulation/examples/forging/``
and ``write_forging_part`` makes them again (tests/simulation/test_forging_part.py checks they agree).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from services.inspection.materials import builtin_material

EXAMPLE_DIRECTORY = Path(__file__).parent / "examples" / "forging"
PART_FILE = EXAMPLE_DIRECTORY / "part.json"
_MESH_NAME = "forging-cold.stl"
_SEGMENTS = 360
# The hot shapes of presets.forging_scene() along the billet's axis, and the temperatures at their centres
# (services.simulation.thermal.forging_temperatures): billet 1040 degC, flange 960 degC.
_BILLET_RADIUS, _BILLET_HALF_LENGTH, _BILLET_C = 55.0, 110.0, 1040.0
_FLANGE_RADIUS, _FLANGE_X, _FLANGE_HALF_LENGTH, _FLANGE_C = 80.0, -95.0, 12.0, 960.0


def _scales() -> tuple[float, float]:
    steel = builtin_material("carbon-steel")
    billet, flange = steel.strain(np.array([_BILLET_C, _FLANGE_C]))
    return 1.0 / (1.0 + float(billet)), 1.0 / (1.0 + float(flange))


def forging_profile() -> np.ndarray:
    """The cold forging's profile (x, r) in mm, from the axis at the flange's end round to the axis at the
    billet's free end: lengths shrink with the billet's strain, the flange's radius with its own."""
    billet, flange = _scales()
    x0, x1 = -_BILLET_HALF_LENGTH * billet, _BILLET_HALF_LENGTH * billet
    f0, f1 = (_FLANGE_X - _FLANGE_HALF_LENGTH) * billet, (_FLANGE_X + _FLANGE_HALF_LENGTH) * billet
    r, rf = _BILLET_RADIUS * billet, _FLANGE_RADIUS * flange
    return np.array([[x0, 0.0], [x0, r], [f0, r], [f0, rf], [f1, rf], [f1, r], [x1, r], [x1, 0.0]])


def revolved_mesh(profile: np.ndarray, segments: int = _SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh of ``profile`` (x, r) turned about the x axis; vertices (V, 3), triangles (T, 3).

    The profile starts and ends on the axis (r = 0); the triangles face outward."""
    angles = np.arange(segments) * 2 * np.pi / segments
    vertices, triangles = [], []
    rings = []
    for x, radius in profile:
        if radius == 0.0:
            rings.append(len(vertices))
            vertices.append([x, 0.0, 0.0])
        else:
            rings.append(len(vertices))
            vertices.extend(np.column_stack([np.full(segments, x), radius * np.cos(angles), radius * np.sin(angles)]))
    k = np.arange(segments)
    for (xa, ra), (xb, rb), a, b in zip(profile[:-1], profile[1:], rings[:-1], rings[1:]):
        if ra == 0.0:
            triangles.extend(np.column_stack([np.full(segments, a), b + (k + 1) % segments, b + k]))
        elif rb == 0.0:
            triangles.extend(np.column_stack([a + k, a + (k + 1) % segments, np.full(segments, b)]))
        else:
            triangles.extend(np.column_stack([a + k, a + (k + 1) % segments, b + (k + 1) % segments]))
            triangles.extend(np.column_stack([a + k, b + (k + 1) % segments, b + k]))
    vertices, triangles = np.asarray(vertices, dtype=np.float64), np.asarray(triangles, dtype=np.int64)
    # Outward: the enclosed volume (divergence theorem) of a closed mesh is positive when its triangles face out.
    corners = vertices[triangles]
    volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6.0
    return vertices, triangles if volume > 0 else triangles[:, ::-1].copy()


def forging_part_definition() -> dict:
    """The part file (docs/part-file.md) of the cold forging: the billet's and the flange's diameters and the
    surface. The station's projector lights neither end face, so no length between them is measured."""
    (x0, _), _, (f0, _), (_, rf), (f1, _), _, (x1, r), _ = forging_profile()

    def box(low, high):
        return {"min": [round(v, 3) for v in low], "max": [round(v, 3) for v in high]}

    return {
        "version": 1, "name": "simulated-forging", "material": "carbon-steel", "nominal": _MESH_NAME,
        "features": [
            {"name": "billet_diameter", "type": "cylinder", "measure": "diameter",
             "region": box((f1 + 15, -r - 3, -r - 3), (x1 - 15, r + 3, r + 3)),
             "nominal": round(2 * r, 3), "tolerance": [-0.3, 0.3]},
            {"name": "flange_diameter", "type": "cylinder", "measure": "diameter",
             "region": box((f0 + 3, -rf - 3, -rf - 3), (f1 - 3, rf + 3, rf + 3)),
             "nominal": round(2 * rf, 3), "tolerance": [-0.4, 0.4]},
        ],
        "surface_tolerance": [-1.0, 1.0],
    }


def part_file_text(definition: dict) -> str:
    """The part file as JSON, one feature per line."""
    features = ",\n  ".join(json.dumps(feature) for feature in definition["features"])
    head = {key: value for key, value in definition.items() if key not in ("features", "surface_tolerance")}
    return (json.dumps(head)[:-1] + f',\n "features": [\n  {features}],\n'
            f' "surface_tolerance": {json.dumps(definition["surface_tolerance"])}}}\n')


def write_forging_part(directory: Path) -> Path:
    """Write the part file and its STL mesh into ``directory``; return the part file's path."""
    import open3d as o3d

    directory.mkdir(parents=True, exist_ok=True)
    vertices, triangles = revolved_mesh(forging_profile())
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(directory / _MESH_NAME), mesh, write_ascii=False)
    part = directory / "part.json"
    part.write_text(part_file_text(forging_part_definition()))
    return part
