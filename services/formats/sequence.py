"""The sequence manifest ``sequence.json``: which projected pattern each captured frame shows (a public format).

The manifest lists the frames in display order; each names its image ``file``
and what it encodes. It describes this project's default sequence and the
sequences of other scanners alike, so that any of them can be decoded. The
full reference, with the pattern equations and examples, is
docs/sequence-manifest.md.

```json
{"version": 1,
 "projector": {"width": 1824, "height": 1140},
 "frames": [{"file": "white.png", "kind": "white"},
            {"file": "black.png", "kind": "black"},
            {"file": "gx10.png", "kind": "gray", "axis": "x", "bit": 10},
            {"file": "px0.png", "kind": "phase", "axis": "x", "period": 16, "step": 0, "steps": 8}]}
```

Pattern equations, with ``c`` the projector pixel-centre coordinate along
``axis`` (column index for x, row index for y; pixel centres at integers):

- ``gray``: lit where bit ``bit`` of the reflected binary Gray code
  ``g(c) = c XOR (c >> 1)`` is 1 (unlit there when ``inverted``).
- ``phase``: ``I(c) = 1/2 + 1/2 cos(2 pi c / period - 2 pi step / steps)``.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.errors import InputError
from services.formats.images import read_frame_stack
from services.formats.files import write_text_atomically
from services.formats.json_files import read_text, validate_json

MANIFEST_NAME = "sequence.json"
Axis = Literal["x", "y"]
AXES: tuple[Axis, Axis] = ("x", "y")


class _Frame(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    file: str = Field(min_length=1, description="Image file name, relative to the manifest's directory.")

    def _check_file_name(self) -> None:
        if Path(self.file).name != self.file:
            raise ValueError(f"file {self.file!r} must be a plain file name in the capture directory, not a path")


class WhiteFrame(_Frame):
    """The projector fully lit: the reference for 'on'."""

    kind: Literal["white"]


class BlackFrame(_Frame):
    """The projector fully dark: the reference for 'off' (ambient light and glow)."""

    kind: Literal["black"]


class GrayFrame(_Frame):
    """One bit plane of the Gray code of the projector coordinate along ``axis``."""

    kind: Literal["gray"]
    axis: Axis
    bit: int = Field(ge=0, le=30, description="Bit of g(c) = c XOR (c >> 1); 0 is the finest (1-pixel stripes).")
    inverted: bool = Field(default=False, description="True for the inverse (complement) of the plane.")


class PhaseFrame(_Frame):
    """Step ``step`` of an N-step phase-shifted sinusoid along ``axis``."""

    kind: Literal["phase"]
    axis: Axis
    period: float = Field(gt=0, description="Sinusoid period in projector pixels.")
    step: int = Field(ge=0, description="k in I = 1/2 + 1/2 cos(2 pi c / period - 2 pi k / steps).")
    steps: int = Field(ge=3, description="N, the number of equally spaced phase shifts.")

    @model_validator(mode="after")
    def _step_in_range(self) -> PhaseFrame:
        if self.step >= self.steps:
            raise ValueError(f"step {self.step} is out of range for steps {self.steps} (must be 0..{self.steps - 1})")
        return self


Frame = Annotated[WhiteFrame | BlackFrame | GrayFrame | PhaseFrame, Field(discriminator="kind")]


class ProjectorSize(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    width: int = Field(gt=0, le=1 << 16)
    height: int = Field(gt=0, le=1 << 16)


class GrayPlane(BaseModel):
    """One Gray-code bit as decoded: the frame showing it and, if projected, its complement."""

    model_config = ConfigDict(frozen=True)

    bit: int
    frame: int
    inverted: bool
    complement: int | None


class PhaseGroup(BaseModel):
    """The N frames of one phase-shifted sinusoid, ordered by step."""

    model_config = ConfigDict(frozen=True)

    period: float
    frames: tuple[int, ...]


class Sequence(BaseModel):
    """The frames of one structured-light sequence in display order, and what each encodes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    version: Literal[1] = 1
    projector: ProjectorSize
    frames: list[Frame] = Field(min_length=1)

    @model_validator(mode="after")
    def _frames_are_consistent(self) -> Sequence:
        for frame in self.frames:
            frame._check_file_name()
        for name, count in Counter(frame.file for frame in self.frames).items():
            if count > 1:
                raise ValueError(f"frames: file {name!r} is listed {count} times; each frame needs its own file")
        whites = [i for i, frame in enumerate(self.frames) if frame.kind == "white"]
        if len(whites) > 1:
            raise ValueError(f"frames[{whites[1]}]: a second white frame; a sequence has at most one")
        blacks = [i for i, frame in enumerate(self.frames) if frame.kind == "black"]
        if len(blacks) > 2 or (len(blacks) == 2 and blacks[1] != len(self.frames) - 1):
            raise ValueError(f"frames[{blacks[1]}]: a second black frame that is not the last frame; a sequence "
                             "has at most one black frame, and a second one only to close it (the glow's drift)")
        self._check_gray_planes()
        self._check_phase_groups()
        for axis in AXES:
            self._check_axis_can_be_decoded(axis)
        if not self.coded_axes:
            raise ValueError("frames: no Gray-code or phase frame; the sequence codes no projector axis")
        return self

    def _check_gray_planes(self) -> None:
        seen: dict[tuple[str, int, bool], int] = {}
        for index, frame in enumerate(self.frames):
            if frame.kind != "gray":
                continue
            key = (frame.axis, frame.bit, frame.inverted)
            if key in seen:
                raise ValueError(
                    f"frames[{index}]: axis {frame.axis} bit {frame.bit} (inverted={frame.inverted}) "
                    f"is already shown by frames[{seen[key]}]"
                )
            seen[key] = index
            if frame.bit >= self.code_bits(frame.axis):
                raise ValueError(
                    f"frames[{index}]: bit {frame.bit} is above the most significant bit "
                    f"{self.code_bits(frame.axis) - 1} of a {self.axis_size(frame.axis)}-pixel axis {frame.axis}"
                )
        for axis in AXES:
            bits = sorted({bit for (a, bit, _) in seen if a == axis})
            if bits and bits != list(range(bits[0], self.code_bits(axis))):
                missing = sorted(set(range(bits[0], self.code_bits(axis))) - set(bits))
                raise ValueError(
                    f"frames: the Gray code of axis {axis} lacks bit(s) {missing}; the coded bits must run without "
                    f"a gap from the finest one shown ({bits[0]}) to the most significant ({self.code_bits(axis) - 1})"
                )

    def _check_phase_groups(self) -> None:
        groups: dict[tuple[str, float], list[int]] = {}
        for index, frame in enumerate(self.frames):
            if frame.kind == "phase":
                groups.setdefault((frame.axis, frame.period), []).append(index)
        for (axis, period), indices in groups.items():
            steps = {self.frames[i].steps for i in indices}
            if len(steps) > 1:
                raise ValueError(
                    f"frames[{indices[0]}]: the axis {axis} period {period:g} frames disagree on steps ({sorted(steps)})"
                )
            count = steps.pop()
            shown = Counter(self.frames[i].step for i in indices)
            repeated = [step for step, n in shown.items() if n > 1]
            if repeated:
                raise ValueError(f"frames: axis {axis} period {period:g} shows step {repeated[0]} more than once")
            if len(shown) != count:
                missing = sorted(set(range(count)) - set(shown))
                raise ValueError(f"frames: axis {axis} period {period:g} of {count} steps lacks step(s) {missing}")

    def _check_axis_can_be_decoded(self, axis: Axis) -> None:
        planes = self.gray_planes(axis)
        groups = self.phase_groups(axis)
        references = self.white_index is not None and self.black_index is not None
        if any(plane.complement is None for plane in planes) and not references and not self.phase_groups():
            plane = next(plane for plane in planes if plane.complement is None)
            raise ValueError(
                f"frames[{plane.frame}]: axis {axis} Gray bit {plane.bit} has no inverse frame and the sequence has "
                "neither a white and a black frame nor phase frames to threshold it against"
            )
        if not groups:
            return
        if planes:
            stripe = 1 << planes[0].bit
            if stripe > groups[0].period:
                raise ValueError(
                    f"frames: axis {axis} Gray stripes are {stripe} px wide, wider than the coarsest phase period "
                    f"{groups[0].period:g} px, so the phase cannot be unwrapped; show Gray bit "
                    f"{int(math.floor(math.log2(groups[0].period)))} or finer"
                )
        elif groups[0].period < self.axis_size(axis):
            raise ValueError(
                f"frames: axis {axis} has no Gray code and its coarsest phase period {groups[0].period:g} px is "
                f"shorter than the axis ({self.axis_size(axis)} px), so the phase cannot be unwrapped"
            )

    def axis_size(self, axis: Axis) -> int:
        """Projector pixels along ``axis``."""
        return self.projector.width if axis == "x" else self.projector.height

    def code_bits(self, axis: Axis) -> int:
        """Bits of the Gray code of a coordinate along ``axis``: ceil(log2(size)), at least 1."""
        return max(1, (self.axis_size(axis) - 1).bit_length())

    @property
    def white_index(self) -> int | None:
        return next((i for i, frame in enumerate(self.frames) if frame.kind == "white"), None)

    @property
    def black_index(self) -> int | None:
        return next((i for i, frame in enumerate(self.frames) if frame.kind == "black"), None)

    @property
    def closing_black_index(self) -> int | None:
        """The second black frame, which closes the sequence so that a drifting offset (a hot part's
        cooling glow) can be interpolated between the two; None when there is none."""
        blacks = [i for i, frame in enumerate(self.frames) if frame.kind == "black"]
        return blacks[1] if len(blacks) == 2 else None

    @property
    def coded_axes(self) -> tuple[Axis, ...]:
        """Axes with Gray-code or phase frames."""
        return tuple(axis for axis in AXES if self.gray_planes(axis) or self.phase_groups(axis))

    def gray_planes(self, axis: Axis) -> list[GrayPlane]:
        """The Gray-code bits shown for ``axis``, finest first, each with its complement if shown."""
        by_key = {
            (frame.bit, frame.inverted): index
            for index, frame in enumerate(self.frames)
            if frame.kind == "gray" and frame.axis == axis
        }
        planes = []
        for bit in sorted({bit for bit, _ in by_key}):
            if (bit, False) in by_key:
                planes.append(GrayPlane(bit=bit, frame=by_key[bit, False], inverted=False,
                                        complement=by_key.get((bit, True))))
            else:
                planes.append(GrayPlane(bit=bit, frame=by_key[bit, True], inverted=True, complement=None))
        return planes

    def phase_groups(self, axis: Axis | None = None) -> list[PhaseGroup]:
        """The phase-shifted sinusoids along ``axis`` (all axes if None), coarsest period first."""
        groups: dict[tuple[str, float], dict[int, int]] = {}
        for index, frame in enumerate(self.frames):
            if frame.kind == "phase" and (axis is None or frame.axis == axis):
                groups.setdefault((frame.axis, frame.period), {})[frame.step] = index
        ordered = sorted(groups.items(), key=lambda item: -item[0][1])
        return [
            PhaseGroup(period=period, frames=tuple(steps[k] for k in sorted(steps)))
            for (_, period), steps in ordered
        ]


_FRAME_KINDS = frozenset({"white", "black", "gray", "phase"})


def parse_sequence(text: str, source: str = MANIFEST_NAME) -> Sequence:
    """Validate manifest JSON text; errors name ``source`` and the field."""
    return validate_json(Sequence, text, source, tags=_FRAME_KINDS)


def sequence_to_json(sequence: Sequence) -> str:
    return json.dumps(sequence.model_dump(mode="json"), indent=2)


def load_sequence(directory: str | Path) -> Sequence:
    """Read and validate ``directory/sequence.json``."""
    path = Path(directory) / MANIFEST_NAME
    return parse_sequence(read_text(path, "sequence manifest"), str(path))


def save_sequence(sequence: Sequence, directory: str | Path) -> Path:
    """Write ``directory/sequence.json`` atomically and return its path."""
    return write_text_atomically(Path(directory) / MANIFEST_NAME, sequence_to_json(sequence) + "\n")


def read_capture(directory: str | Path, manifest: str | Path | None = None) -> tuple[Sequence, np.ndarray]:
    """Read a capture directory: its manifest and the camera frames it names, in display order.

    Parameters
    ----------
    directory : path
        The capture directory; frame file names are relative to it.
    manifest : path, optional
        The manifest to use instead of ``directory/sequence.json``: for captures made by other
        software (which write no manifest) or kept read-only, one manifest serves them all.

    Returns
    -------
    sequence : Sequence
    frames : (F, H, W) uint8 or uint16 array
        One camera frame per manifest frame.

    Raises
    ------
    InputError
        Naming the file, for a missing or invalid manifest, a missing or
        unreadable frame, frames of different sizes or bit depths, or a black
        frame brighter than the white one (frames out of the manifest's order).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"{directory}: capture directory does not exist")
    if manifest is None:
        sequence = load_sequence(directory)
    else:
        sequence = parse_sequence(read_text(manifest, "sequence manifest"), str(manifest))
    frames = read_frame_stack([directory / frame.file for frame in sequence.frames])
    _check_references(sequence, frames, directory)
    return sequence, frames


def _check_references(sequence: Sequence, frames: np.ndarray, directory: Path) -> None:
    """Refuse a capture whose black frame is brighter than its white one: the manifest's order is wrong."""
    white, black = sequence.white_index, sequence.black_index
    if white is None or black is None:
        return
    white_mean, black_mean = float(frames[white].mean()), float(frames[black].mean())
    if black_mean > white_mean + 0.005 * np.iinfo(frames.dtype).max:
        raise InputError(
            f"{directory / sequence.frames[black].file}: the black frame is brighter than the white frame "
            f"{sequence.frames[white].file} (mean grey level {black_mean:.1f} against {white_mean:.1f}); "
            f"the frames do not match the order in {MANIFEST_NAME}"
        )
