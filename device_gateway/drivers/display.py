"""A projector driven as a full-screen display output through SDL (pygame).

OpenCV is installed headless here (no GUI), so its ``namedWindow`` cannot open a
screen; SDL can, on a chosen display of a multi-monitor desktop. When no display is
reachable SDL silently falls back to an off-screen driver: that is refused with a
clear error, unless the off-screen driver was asked for explicitly through
``SDL_VIDEODRIVER`` (useful for headless checks).

SDL wants its window driven from the thread that created it, while the gateway calls
drivers from whichever HTTP worker thread runs the capture: every SDL call therefore
runs on one thread of the projector's own.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from device_gateway.devices import DeviceInfo, DeviceUnavailable, ProjectorDriver

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
import pygame  # noqa: E402  (after the variable that silences its banner)

_HEADLESS_DRIVERS = ("offscreen", "dummy")


class DisplayProjector(ProjectorDriver):
    """A projector connected as display number ``display`` and driven full screen at its native size."""

    def __init__(self, name: str = "projector", width: int = 1280, height: int = 800, display: int = 0,
                 settle_s: float = 0.1) -> None:
        self.name = name
        self.width, self.height = width, height
        self.display = display
        self._settle_s = settle_s
        self._surface: pygame.Surface | None = None
        self._sdl = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"projector-{name}")

    @property
    def info(self) -> DeviceInfo:
        return DeviceInfo(self.name, "projector", "display", self.width, self.height, model=f"display {self.display}")

    @property
    def settle_s(self) -> float:
        return self._settle_s

    @property
    def is_open(self) -> bool:
        return self._surface is not None and pygame.display.get_init()

    def open(self) -> None:
        self._sdl.submit(self._open).result()

    def close(self) -> None:
        self._sdl.submit(self._close).result()

    def show(self, pattern: np.ndarray) -> None:
        if self._surface is None:
            raise DeviceUnavailable(f"projector {self.name!r} is not open")
        grey = np.asarray(pattern)
        if grey.shape != (self.height, self.width) or grey.dtype != np.uint8:
            raise ValueError(f"Projector {self.name!r} shows ({self.height}, {self.width}) uint8 patterns; "
                             f"got {grey.shape} {grey.dtype}.")
        self._sdl.submit(self._show, grey).result()

    def _open(self) -> None:
        try:
            pygame.display.init()
        except pygame.error as error:
            raise DeviceUnavailable(f"projector {self.name!r}: no display to draw on ({error})") from None
        driver = pygame.display.get_driver()
        if driver in _HEADLESS_DRIVERS and os.environ.get("SDL_VIDEODRIVER") != driver:
            pygame.display.quit()
            raise DeviceUnavailable(
                f"projector {self.name!r}: no display is reachable (SDL fell back to its {driver!r} driver); "
                "run the gateway on the machine the projector is plugged into, with DISPLAY or WAYLAND_DISPLAY set"
            )
        displays = pygame.display.get_num_displays()
        if not 0 <= self.display < displays:
            pygame.display.quit()
            raise DeviceUnavailable(
                f"projector {self.name!r}: display {self.display} does not exist (displays 0..{displays - 1})"
            )
        surface = pygame.display.set_mode((self.width, self.height), pygame.FULLSCREEN | pygame.NOFRAME,
                                          display=self.display)
        if surface.get_size() != (self.width, self.height):
            pygame.display.quit()
            raise DeviceUnavailable(
                f"projector {self.name!r}: display {self.display} runs at "
                f"{surface.get_width()}x{surface.get_height()}, "
                f"not the projector's {self.width}x{self.height}; set the display to the projector's native mode"
            )
        pygame.mouse.set_visible(False)
        self._surface = surface

    def _close(self) -> None:
        self._surface = None
        pygame.display.quit()

    def _show(self, grey: np.ndarray) -> None:
        # pygame surfaces are indexed (x, y): transpose the (row, column) image, grey to RGB.
        pygame.surfarray.blit_array(self._surface, np.repeat(grey.T[:, :, None], 3, axis=2))
        pygame.display.flip()
        pygame.event.pump()  # keeps the window responsive to the window manager
