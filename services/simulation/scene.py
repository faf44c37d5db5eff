"""The virtual scene: analytic surfaces and triangle meshes with albedo, plus ambient light (a public format).

```json
{"ambient": 0.05,
 "surfaces": [
   {"type": "plane", "center": [0, 0, 500], "normal": [0, 0, -1], "u_axis": [1, 0, 0], "size": [300, 200],
    "albedo": {"base": 0.7, "texture_amplitude": 0.1, "feature_size": 15, "seed": 3}},
   {"type": "sphere", "center": [0, 0, 480], "radius": 100},
   {"type": "cylinder", "center": [0, 0, 600], "axis": [1, 0, 0], "radius": 60, "length": 200, "capped": true},
   {"type": "mesh", "vertices": [[0, 0, 400], [10, 0, 400], [0, 10, 400]], "faces": [[0, 1, 2]]},
   {"type": "mesh", "ply": "part.ply"}]}
```

Millimetres in the world frame of the rig. A mesh is given inline or as a PLY file (a ``vertex``
element with x, y, z and a ``face`` element of triangles) whose path is relative to the scene file.
Unknown fields are refused so that a typo is not silently ignored. See docs/simulator.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from plyfile import PlyData
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from services.errors import InputError
from services.formats.json_files import describe_validation_error, read_text, validate_json
from services.simulation.optics import Optics
from services.simulation.temperature import TemperatureScene

Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
_TEXTURE_WAVES = 8


def _unit(vector: list[float], name: str) -> np.ndarray:
    array = np.asarray(vector, dtype=np.float64)
    norm = np.linalg.norm(array)
    if not np.isfinite(norm) or norm == 0:
        raise ValueError(f"{name} must be a finite non-zero vector")
    return array / norm


class Albedo(BaseModel):
    """Diffuse reflectance: a base value plus an optional smooth procedural texture.

    The texture is a sum of 8 plane waves in 3-D with random directions and phases drawn
    from ``seed`` and wavelength ``feature_size`` mm, scaled to lie in [-1, 1]:
    albedo(X) = clip(base + texture_amplitude * w(X), 0, 1).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    base: float = Field(0.8, ge=0.0, le=1.0)
    texture_amplitude: float = Field(0.0, ge=0.0, le=1.0)
    feature_size: float = Field(20.0, gt=0.0)
    seed: int = Field(0, ge=0)

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Albedo at world points (N, 3) -> (N,)."""
        points = np.asarray(points, dtype=np.float64)
        if self.texture_amplitude == 0:
            return np.full(len(points), self.base)
        rng = np.random.default_rng(self.seed)
        directions = rng.normal(size=(_TEXTURE_WAVES, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        phases = rng.uniform(0, 2 * np.pi, _TEXTURE_WAVES)
        # float32 halves the cost; the texture is smooth, so its precision (1e-4 mm at 1 m) is ample
        wave_vectors = (directions.T * (2 * np.pi / self.feature_size)).astype(np.float32)
        waves = np.cos(points.astype(np.float32) @ wave_vectors + phases.astype(np.float32))
        return np.clip(self.base + self.texture_amplitude * waves.mean(axis=1), 0.0, 1.0)


class _Surface(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    albedo: Albedo = Field(default_factory=Albedo)


class Plane(_Surface):
    """A finite rectangle: ``size`` = [extent along ``u_axis``, extent along normal x u_axis] in mm."""

    type: Literal["plane"] = "plane"
    center: Vector3
    normal: Vector3
    u_axis: Vector3
    size: Annotated[list[Annotated[float, Field(gt=0)]], Field(min_length=2, max_length=2)]

    @model_validator(mode="after")
    def _axes_are_perpendicular(self) -> Plane:
        normal = _unit(self.normal, "normal")
        u_axis = _unit(self.u_axis, "u_axis")
        if abs(normal @ u_axis) > 1e-6:
            raise ValueError("u_axis must be perpendicular to normal")
        return self

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit (normal, u, v) with v = normal x u."""
        normal = _unit(self.normal, "normal")
        u_axis = _unit(self.u_axis, "u_axis")
        return normal, u_axis, np.cross(normal, u_axis)


class Sphere(_Surface):
    type: Literal["sphere"] = "sphere"
    center: Vector3
    radius: float = Field(gt=0)


class Cylinder(_Surface):
    """A right circular cylinder of ``length`` mm centred on ``center`` along ``axis``, capped by disks or open."""

    type: Literal["cylinder"] = "cylinder"
    center: Vector3
    axis: Vector3
    radius: float = Field(gt=0)
    length: float = Field(gt=0)
    capped: bool = True

    @field_validator("axis")
    @classmethod
    def _axis_is_a_direction(cls, axis: list[float]) -> list[float]:
        _unit(axis, "axis")
        return axis


class Mesh(_Surface):
    """A triangle mesh, inline (``vertices``, ``faces``) or from a PLY file (``ply``, resolved by load_scene)."""

    type: Literal["mesh"] = "mesh"
    vertices: list[Vector3] | None = None
    faces: list[Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=3, max_length=3)]] | None = None
    ply: str | None = None

    @model_validator(mode="after")
    def _one_source(self) -> Mesh:
        inline = self.vertices is not None or self.faces is not None
        if inline == (self.ply is not None):
            raise ValueError("a mesh needs either 'vertices' and 'faces' or 'ply', not both or neither")
        if inline:
            if not self.vertices or not self.faces:
                raise ValueError("an inline mesh needs non-empty 'vertices' and 'faces'")
            if max(max(face) for face in self.faces) >= len(self.vertices):
                raise ValueError(f"faces refer to a vertex index beyond the {len(self.vertices)} vertices")
        return self

    def triangles(self) -> np.ndarray:
        """(T, 3, 3) array of triangle corners in world mm."""
        if self.vertices is None:
            raise ValueError(f"The mesh from {self.ply!r} is not loaded; read the scene with load_scene.")
        return np.asarray(self.vertices, dtype=np.float64)[np.asarray(self.faces, dtype=np.int64)]


Surface = Annotated[Plane | Sphere | Cylinder | Mesh, Field(discriminator="type")]


class Scene(BaseModel):
    """Surfaces in the rig's world frame and the ambient light level (fraction of full projector light).

    A hot part's scene adds ``temperature`` (one field per surface, degrees Celsius, optionally cooling)
    and ``optics`` (projector spectrum, camera filter, sensor, emissivity: what the visible camera makes
    of the parts' glow); see docs/hot-parts.md.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    surfaces: list[Surface] = Field(min_length=1)
    ambient: float = Field(0.05, ge=0.0, le=1.0)
    temperature: TemperatureScene | None = None
    optics: Optics | None = None

    @model_validator(mode="after")
    def _one_temperature_field_per_surface(self) -> Scene:
        if self.temperature is not None and len(self.temperature.surfaces) != len(self.surfaces):
            raise ValueError(f"temperature: {len(self.temperature.surfaces)} surface fields for "
                             f"{len(self.surfaces)} surfaces; give one per surface, in the same order")
        return self


def surface_albedo(scene: Scene, points: np.ndarray, surface_index: np.ndarray) -> np.ndarray:
    """Albedo of each point (N, 3) on surface ``surface_index`` (N,); NaN where the index is -1."""
    albedo = np.full(len(points), np.nan)
    for index, surface in enumerate(scene.surfaces):
        on_surface = surface_index == index
        if on_surface.any():
            albedo[on_surface] = surface.albedo.evaluate(points[on_surface])
    return albedo


_SURFACE_TYPES = frozenset({"plane", "sphere", "cylinder", "mesh"})


def _read_ply_mesh(path: Path, field: str) -> tuple[list[list[float]], list[list[int]]]:
    try:
        data = PlyData.read(str(path))
        vertex = data["vertex"].data
        vertices = np.column_stack([vertex["x"], vertex["y"], vertex["z"]]).astype(np.float64)
        faces = np.asarray([np.asarray(face, dtype=np.int64) for face in data["face"].data["vertex_indices"]])
    except FileNotFoundError:
        raise InputError(f"{field}: mesh file {path} is missing") from None
    except Exception as error:  # plyfile raises several types for malformed files
        raise InputError(f"{field}: {path} is not a PLY triangle mesh with x, y, z vertices ({error})") from None
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputError(f"{field}: {path} must contain triangles only")
    return vertices.tolist(), faces.tolist()


def parse_scene(text: str, source: str = "scene", base_directory: str | Path = ".") -> Scene:
    """Validate scene JSON text and load its PLY meshes (paths relative to ``base_directory``).

    Errors raise ``InputError`` naming ``source`` and the field.
    """
    scene = validate_json(Scene, text, source, tags=_SURFACE_TYPES)
    surfaces = []
    for index, surface in enumerate(scene.surfaces):
        if isinstance(surface, Mesh) and surface.ply is not None:
            field = f"{source}: surfaces.{index}.ply"
            vertices, faces = _read_ply_mesh(Path(base_directory) / surface.ply, field)
            try:
                surface = Mesh(vertices=vertices, faces=faces, albedo=surface.albedo)
            except ValidationError as error:
                raise InputError(describe_validation_error(field, error)) from None
        surfaces.append(surface)
    return scene.model_copy(update={"surfaces": surfaces})


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file."""
    path = Path(path)
    return parse_scene(read_text(path, "scene file"), str(path), path.parent)
