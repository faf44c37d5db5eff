"""A simulated station and billet for the inspection tests: the forging rig at 35 % resolution."""

from dataclasses import dataclass

import numpy as np
import pytest

from services.formats.part import load_part
from services.inspection.inspect import prepare_part
from services.simulation.hot_part import HotPart, billet_pose, cylinder_mesh, simulated_field, write_billet_part
from services.simulation.presets import forging_rig
from services.simulation.thermal import SurfaceTemperature

SEGMENTS = 180


@dataclass
class Station:
    part_path: object
    part: object
    prepared: object
    rig: object

    def scan(self, seed=0, diameter=90.0, temperature=SurfaceTemperature(base=1000.0), bumps=(), pose=None):
        """A field of the billet of true cold ``diameter`` (its nominal is 90 mm) and its hot truth points."""
        vertices, triangles = cylinder_mesh(diameter / 2, 200.0, SEGMENTS)
        hot = HotPart(vertices, triangles, self.part.material, temperature,
                      pose=billet_pose() if pose is None else pose, bumps=tuple(bumps))
        devices = self.rig.devices
        return simulated_field(hot, devices["camera"], devices["projector"], devices["thermal"],
                               np.random.default_rng(seed))


@pytest.fixture(scope="session")
def station(tmp_path_factory):
    path = write_billet_part(tmp_path_factory.mktemp("billet"), segments=SEGMENTS)
    part = load_part(path)
    return Station(path, part, prepare_part(part), forging_rig(0.35))
