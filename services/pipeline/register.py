"""Use cases: register an infrared image onto a visible one, and a stored scan's thermal frame onto its
white camera frame, by mutual information."""

from __future__ import annotations

from typing import Any

import numpy as np

from services.errors import InputError
from services.formats.sequence import Sequence
from services.registration.overlay import fused_overlay
from services.registration.register import Registration, register


def register_pair(*, fixed: np.ndarray, moving: np.ndarray, model: str = "similarity", source: str = "the pair",
                  **options: Any) -> Registration:
    """:func:`services.registration.register.register` of ``moving`` onto ``fixed``; ``options`` are its
    keyword arguments. Bad input raises an ``InputError`` naming ``source``."""
    try:
        return register(fixed, moving, model, **options)
    except ValueError as error:
        raise InputError(f"{source}: {error}") from None


def white_frame(frames: np.ndarray, sequence: Sequence) -> np.ndarray:
    """The capture's frame under full white light."""
    for index, frame in enumerate(sequence.frames):
        if frame.kind == "white":
            return frames[index]
    raise InputError("the scan's sequence has no white frame to register the thermal frame against")


def register_scan(*, frames: np.ndarray, sequence: Sequence, thermal: np.ndarray,
                  model: str = "similarity") -> tuple[Registration, np.ndarray]:
    """Register a scan's first thermal frame onto its white camera frame; also returns the fused overlay."""
    visible = white_frame(frames, sequence)
    infrared = thermal[0] if thermal.ndim == 3 else thermal
    registration = register_pair(fixed=visible, moving=infrared, model=model, source="the scan")
    return registration, fused_overlay(visible, infrared, registration.matrix)
