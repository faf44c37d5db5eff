"""A point cloud or temperature field: equal-length per-point arrays, their units and metadata.

Structured light makes a cloud (``x, y, z`` in world millimetres, normals and decoding properties);
fusion adds ``temperature`` (degrees Celsius, NaN unseen), ``view_angle`` and colours, which makes it
a temperature field. ``services.formats.ply`` writes and reads it as binary PLY, bytes or file.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

# Units of the properties thermofield writes; a property missing here is dimensionless or a count.
PROPERTY_UNITS = MappingProxyType({
    "x": "mm", "y": "mm", "z": "mm", "u": "px", "v": "px", "projector": "px",
    "temperature": "degC", "view_angle": "deg",
})


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Per-point properties (read-only 1-D arrays of one length), their units and free-text comments.

    ``cloud["x"]`` is a property; ``len(cloud)`` the number of points; ``cloud.points`` the (N, 3)
    float64 coordinates. A cloud is never changed: :meth:`with_properties` and :meth:`without` make new
    ones sharing the unchanged arrays.
    """

    properties: Mapping[str, np.ndarray]
    units: Mapping[str, str] = field(default_factory=dict)
    comments: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        arrays = {}
        for name, values in self.properties.items():
            array = np.asarray(values)
            if array.ndim != 1:
                raise ValueError(f"Point property {name!r} must be a 1-D array; got shape {array.shape}.")
            if array.flags.writeable:
                array = array.view()
                array.flags.writeable = False
            arrays[name] = array
        lengths = {name: len(values) for name, values in arrays.items()}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"All point properties must have the same length; got {lengths}.")
        units = {name: unit for name, unit in {**PROPERTY_UNITS, **self.units}.items() if name in arrays}
        object.__setattr__(self, "properties", MappingProxyType(arrays))
        object.__setattr__(self, "units", MappingProxyType(units))
        object.__setattr__(self, "comments", tuple(self.comments))

    def __getitem__(self, name: str) -> np.ndarray:
        return self.properties[name]

    def __contains__(self, name: object) -> bool:
        return name in self.properties

    def __iter__(self) -> Iterator[str]:
        return iter(self.properties)

    def __len__(self) -> int:
        return len(next(iter(self.properties.values()))) if self.properties else 0

    def keys(self):
        return self.properties.keys()

    def values(self):
        return self.properties.values()

    def items(self):
        return self.properties.items()

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float64 world coordinates, millimetres."""
        missing = [name for name in ("x", "y", "z") if name not in self.properties]
        if missing:
            raise ValueError(f"The cloud lacks the coordinate properties {missing}.")
        return np.column_stack([self["x"], self["y"], self["z"]]).astype(np.float64)

    @property
    def has_temperature(self) -> bool:
        return "temperature" in self.properties

    def with_properties(self, comments: tuple[str, ...] | None = None, **properties: np.ndarray) -> PointCloud:
        """A cloud with ``properties`` added or replaced (and ``comments`` replaced when given)."""
        return PointCloud({**self.properties, **properties}, self.units,
                          self.comments if comments is None else comments)

    def without(self, *names: str) -> PointCloud:
        """A cloud without the named properties."""
        return PointCloud({n: v for n, v in self.properties.items() if n not in names}, self.units, self.comments)
