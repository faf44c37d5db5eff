"""A small simulated capture (the paper's rig at a quarter of its resolution, a plane at 500 mm)."""

from dataclasses import dataclass

import numpy as np
import pytest

from services.formats.rig import Rig
from services.formats.sequence import Sequence
from services.simulation.presets import paper_plane, paper_rig
from services.simulation.render import CameraEffects, render_frames, render_view
from services.structured_light.patterns import generate_sequence


def _quarter_size(device):
    K = device.K.copy()
    K[:2] /= 4
    K[:2, 2] = (K[:2, 2] * 4 + 0.5) / 4 - 0.5
    return device.replace(width=device.width // 4, height=device.height // 4, K=K)


@dataclass(frozen=True)
class SmallCapture:
    rig: Rig
    sequence: Sequence
    frames: np.ndarray


@pytest.fixture(scope="session")
def small_capture() -> SmallCapture:
    rig = Rig({name: _quarter_size(device) for name, device in paper_rig().devices.items()})
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    sequence, patterns = generate_sequence(projector.width, projector.height)
    view = render_view(paper_plane(500.0), camera, projector, supersample=1)
    frames = render_frames(view, patterns, np.random.default_rng(0), CameraEffects(noise_sigma=0.5))
    return SmallCapture(rig, sequence, frames)
