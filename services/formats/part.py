"""The part file: the nominal (cold) part, its material, its features and tolerances (a public format).

```json
{"version": 1, "name": "shaft-90", "material": "carbon-steel", "nominal": "shaft-90.stl",
 "features": [
   {"name": "body_diameter", "type": "cylinder", "measure": "diameter",
    "region": {"min": [-40, -60, -60], "max": [40, 60, 60]}, "nominal": 90.0, "tolerance": [-0.3, 0.3]},
   {"name": "face_a", "type": "plane", "region": {"min": [-101, -50, -50], "max": [-99, 50, 50]}},
   {"name": "face_b", "type": "plane", "region": {"min": [99, -50, -50], "max": [101, 50, 50]}},
   {"name": "length", "type": "distance", "between": ["face_a", "face_b"], "nominal": 200.0,
    "tolerance": [-0.5, 0.5]}],
 "surface_tolerance": [-1.0, 1.0]}
```

Millimetres in the part's own frame; ``nominal`` is a triangle mesh (STL, PLY or OBJ) whose path is
relative to the part file. Unknown fields are refused. See docs/part-file.md.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from services.errors import InputError
from services.formats.json_files import read_text, validate_json
from services.formats.limits import DEFAULT_MAX_TRIANGLES, check_mesh
from services.inspection.materials import Material, builtin_material
from services.open3d_loader import open3d

PART_FILE_VERSION = 1
MESH_SUFFIXES = (".stl", ".ply", ".obj")
Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Tolerance = Annotated[list[float], Field(min_length=2, max_length=2)]
FeatureType = Literal["plane", "cylinder", "sphere", "distance"]
FORM_MEASURES = ("flatness", "cylindricity", "sphericity", "ovality")
"""Measures of form: never negative, nominal 0, so only their upper tolerance limit can be passed."""
MEASURES: dict[str, tuple[str, ...]] = {
    "plane": ("flatness",),
    "cylinder": ("diameter", "cylindricity", "ovality"),
    "sphere": ("diameter", "sphericity"),
    "distance": ("distance",),
}


def _check_tolerance(tolerance: list[float] | None, name: str) -> None:
    if tolerance is not None:
        low, high = tolerance
        if not (np.isfinite(low) and np.isfinite(high)) or not low <= 0 <= high or low == high:
            raise ValueError(f"{name} must be [lower, upper] deviations with lower <= 0 <= upper and lower < upper; "
                             f"got {tolerance}")


class Region(BaseModel):
    """An axis-aligned box in the part frame selecting the points a feature is fitted to."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    min: Vector3
    max: Vector3

    @model_validator(mode="after")
    def _is_a_box(self) -> Region:
        if not all(np.isfinite(self.min + self.max)) or any(a >= b for a, b in zip(self.min, self.max)):
            raise ValueError(f"min must lie below max on every axis; got min {self.min}, max {self.max}")
        return self

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether each point (N, 3) lies in the box."""
        inside = np.ones(len(points), dtype=bool)
        for axis in range(3):  # column by column: numpy's reduction over the short axis is several times slower
            column = points[:, axis]
            inside &= (column >= self.min[axis]) & (column <= self.max[axis])
        return inside


class Feature(BaseModel):
    """A fitted geometric element (plane, cylinder, sphere) or a ``distance`` between two of them.

    With a ``measure`` the feature is checked (``nominal`` and ``tolerance`` required); a plane,
    cylinder or sphere without one is a datum that distances refer to.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1, max_length=100)
    type: FeatureType
    measure: str | None = None
    region: Region | None = None
    between: Annotated[list[str], Field(min_length=2, max_length=2)] | None = None
    nominal: float | None = Field(None, ge=0)
    tolerance: Tolerance | None = None

    @model_validator(mode="after")
    def _consistent(self) -> Feature:
        if self.type == "distance":
            if self.between is None or self.region is not None:
                raise ValueError("a distance needs 'between' (two feature names) and no 'region'")
            if self.measure not in (None, "distance"):
                raise ValueError(f"a distance measures 'distance', not {self.measure!r}")
            object.__setattr__(self, "measure", "distance")
        elif self.region is None or self.between is not None:
            raise ValueError(f"a {self.type} needs a 'region' and no 'between'")
        if self.measure is not None and self.measure not in MEASURES[self.type]:
            raise ValueError(f"a {self.type} measures one of {list(MEASURES[self.type])}, not {self.measure!r}")
        if self.measure is not None and (self.nominal is None or self.tolerance is None):
            raise ValueError(f"the measure {self.measure!r} needs 'nominal' and 'tolerance'")
        if self.measure is None and (self.nominal is not None or self.tolerance is not None):
            raise ValueError("'nominal' and 'tolerance' need a 'measure'")
        _check_tolerance(self.tolerance, "tolerance")
        return self


class CustomMaterial(BaseModel):
    """A user's material: its thermal elongation Delta l / l against temperature."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("custom", min_length=1)
    elongation: list[Annotated[list[float], Field(min_length=2, max_length=2)]] = Field(min_length=2)
    relative_uncertainty: float = Field(0.05, ge=0, lt=1)
    source: str = "the part file"

    @field_validator("elongation")
    @classmethod
    def _increasing(cls, rows: list[list[float]]) -> list[list[float]]:
        temperatures = np.asarray(rows)[:, 0]
        if np.any(np.diff(temperatures) <= 0):
            raise ValueError(f"the temperatures must increase strictly; got {temperatures.tolist()}")
        return rows


class UncertaintyBudget(BaseModel):
    """Standard uncertainties (k = 1) of the inputs; the report gives expanded ones (k = 2)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    structured_light_noise_mm: float = Field(0.02, ge=0, description="random error of one point along its normal")
    structured_light_systematic_mm: float = Field(
        0.01, ge=0, description="calibration error common to a feature's points (the plane and sphere tables)")
    emissivity: float = Field(0.85, gt=0, le=1, description="the emissivity the temperatures were computed with")
    emissivity_uncertainty: float = Field(0.02, ge=0, lt=1)
    calibration_fraction: float = Field(0.01, ge=0, lt=1,
                                        description="radiometric calibration, a fraction of the reading in degC")
    calibration_min_k: float = Field(1.0, ge=0, description="lower bound of the calibration term, kelvin")
    netd_k: float = Field(0.05, ge=0, description="noise equivalent temperature difference")
    fallback_temperature_k: float = Field(
        30.0, ge=0, description="extra temperature uncertainty of points without their own temperature")
    material_fraction: float | None = Field(
        None, ge=0, lt=1, description="the material table's relative uncertainty; default the material's own")


class Segmentation(BaseModel):
    """How the part's points are told from the rest of the field."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    min_temperature_c: float = Field(
        300.0, description="points at least this hot belong to the part (they seed the alignment)")
    max_distance_mm: float = Field(5.0, gt=0,
                                   description="after alignment, points this near the nominal are the part's")


class PartFile(BaseModel):
    """The part file as written (paths unresolved)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    version: Literal[1]
    name: str = Field(min_length=1, max_length=200)
    material: str | CustomMaterial
    nominal: str = Field(min_length=1)
    features: list[Feature] = Field(default_factory=list)
    surface_tolerance: Tolerance
    defect_threshold_mm: float = Field(0.1, gt=0, description="dents and bulges deeper than this are reported")
    uncertainty: UncertaintyBudget = Field(default_factory=UncertaintyBudget)
    segmentation: Segmentation = Field(default_factory=Segmentation)

    @field_validator("surface_tolerance")
    @classmethod
    def _tolerance(cls, tolerance: list[float]) -> list[float]:
        _check_tolerance(tolerance, "surface_tolerance")
        return tolerance

    @field_validator("nominal")
    @classmethod
    def _mesh_suffix(cls, nominal: str) -> str:
        if Path(nominal).suffix.lower() not in MESH_SUFFIXES:
            raise ValueError(f"the nominal mesh must be one of {', '.join(MESH_SUFFIXES)}; got {nominal!r}")
        return nominal

    @model_validator(mode="after")
    def _references(self) -> PartFile:
        names = [feature.name for feature in self.features]
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise ValueError(f"feature names must be unique; {duplicates} appear more than once")
        fitted = {feature.name for feature in self.features if feature.type != "distance"}
        for feature in self.features:
            for other in feature.between or ():
                if other not in fitted:
                    raise ValueError(f"feature {feature.name!r} refers to {other!r}, which is not a plane, "
                                     "cylinder or sphere of this part")
            if feature.between is not None and feature.between[0] == feature.between[1]:
                raise ValueError(f"feature {feature.name!r} measures a distance from {feature.between[0]!r} to itself")
        if isinstance(self.material, str):
            try:
                builtin_material(self.material)
            except ValueError as error:
                raise ValueError(f"material: {error}") from None
        return self


@dataclass(frozen=True)
class Part:
    """A loaded part: its definition, material table and nominal mesh (part frame, mm)."""

    definition: PartFile
    material: Material
    vertices: np.ndarray  # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int32
    source: str

    @property
    def name(self) -> str:
        return self.definition.name


def _material(definition: PartFile, source: str) -> Material:
    material = definition.material
    try:
        if isinstance(material, str):
            return builtin_material(material)
        table = np.asarray(material.elongation, dtype=np.float64)
        return Material(material.name, table[:, 0], table[:, 1], material.relative_uncertainty, material.source)
    except ValueError as error:
        raise InputError(f"{source}: material: {error}") from None


def read_mesh(path: Path, field: str, shown: str | None = None, *, max_triangles: int = DEFAULT_MAX_TRIANGLES,
              max_bytes: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and triangles (T, 3) of an STL, PLY or OBJ mesh, via Open3D; errors call the file
    ``shown`` (default its path).

    The counts the file declares are checked against its length, ``max_triangles`` and the ``max_bytes`` of
    memory when given, before Open3D reads it (:func:`services.formats.limits.check_mesh`); an error Open3D
    raises is an ``InputError`` naming the file.
    """
    shown = shown or str(path)
    if not path.is_file():
        raise InputError(f"{field}: mesh file {shown} is missing")
    try:
        content = path.read_bytes()
    except OSError as error:
        raise InputError(f"{field}: cannot read {shown} ({error.strerror or error})") from None
    check_mesh(content, path.suffix, f"{field}: {shown}", max_triangles=max_triangles, max_bytes=max_bytes)
    del content
    o3d = open3d()  # loaded (with numba, a second) only for a mesh whose header holds
    try:
        mesh = o3d.io.read_triangle_mesh(str(path))
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        triangles = np.asarray(mesh.triangles, dtype=np.int32)
    except (RuntimeError, MemoryError) as error:  # Open3D's reader errors, a failed allocation
        raise InputError(f"{field}: {shown} cannot be read as a triangle mesh ({type(error).__name__})") from None
    if len(vertices) < 3 or len(triangles) == 0:
        raise InputError(f"{field}: {shown} is not a readable triangle mesh (STL, PLY or OBJ with faces)")
    if not np.isfinite(vertices).all():
        raise InputError(f"{field}: {shown} has non-finite vertex coordinates")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise InputError(f"{field}: {shown} has triangles naming vertices it does not have")
    return vertices, triangles


def parse_part(text: str, source: str = "part", base_directory: str | Path = ".") -> Part:
    """Validate part-file JSON and load its material and nominal mesh (path relative to ``base_directory``)."""
    definition = validate_json(PartFile, text, source, tags=frozenset(MEASURES))
    material = _material(definition, source)
    vertices, triangles = read_mesh(Path(base_directory) / definition.nominal, f"{source}: nominal")
    return Part(definition, material, vertices, triangles, source)


def parse_part_with_mesh(text: str, mesh: bytes, source: str = "part", mesh_source: str = "mesh", *,
                         max_triangles: int = DEFAULT_MAX_TRIANGLES, max_bytes: int | None = None) -> Part:
    """Validate part-file JSON whose nominal mesh is given as bytes (an upload, a stored artifact) in the
    format the part file's ``nominal`` names by its suffix; a bad mesh is an ``InputError`` naming
    ``mesh_source`` (limits as :func:`read_mesh`)."""
    definition = validate_json(PartFile, text, source, tags=frozenset(MEASURES))
    material = _material(definition, source)
    with tempfile.TemporaryDirectory(prefix="thermofield-mesh-") as directory:
        path = Path(directory) / f"nominal{Path(definition.nominal).suffix.lower()}"
        path.write_bytes(mesh)
        vertices, triangles = read_mesh(path, mesh_source, f"the {path.suffix[1:].upper()} mesh",
                                        max_triangles=max_triangles, max_bytes=max_bytes)
    return Part(definition, material, vertices, triangles, source)


def load_part(path: str | Path) -> Part:
    """Read a part file and everything it refers to."""
    path = Path(path)
    return parse_part(read_text(path, "part file"), str(path), path.parent)
