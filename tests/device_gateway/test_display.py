"""The display projector: patterns reach the frame buffer exactly; no display is a clear error."""

from __future__ import annotations

import numpy as np
import pygame
import pytest

from device_gateway.devices import DeviceUnavailable
from device_gateway.drivers.display import DisplayProjector


@pytest.fixture
def no_display(monkeypatch):
    for variable in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"):
        monkeypatch.delenv(variable, raising=False)


@pytest.fixture
def offscreen(monkeypatch):
    """SDL's off-screen video driver, asked for explicitly (a headless check, not a fallback)."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "offscreen")


def test_pattern_is_shown_pixel_for_pixel(offscreen):
    projector = DisplayProjector(width=320, height=200)
    projector.open()
    try:
        pattern = (np.add.outer(np.arange(200) * 7, np.arange(320) * 3) % 256).astype(np.uint8)
        projector.show(pattern)
        shown = pygame.surfarray.array3d(pygame.display.get_surface())
        for channel in range(3):
            np.testing.assert_array_equal(shown[:, :, channel].T, pattern)
        assert projector.is_open
        with pytest.raises(ValueError, match="uint8 patterns"):
            projector.show(np.zeros((200, 321), np.uint8))
    finally:
        projector.close()
    assert not projector.is_open


def test_no_display_is_a_clear_error(no_display):
    projector = DisplayProjector()
    with pytest.raises(DeviceUnavailable, match="no display is reachable"):
        projector.open()
    assert not projector.is_open


def test_a_display_number_that_does_not_exist_is_refused(offscreen):
    with pytest.raises(DeviceUnavailable, match="display 5 does not exist"):
        DisplayProjector(display=5).open()


def test_show_before_open_is_refused():
    with pytest.raises(DeviceUnavailable, match="not open"):
        DisplayProjector().show(np.zeros((800, 1280), np.uint8))
