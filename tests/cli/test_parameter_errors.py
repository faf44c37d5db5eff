"""A use case's error names its parameter; the command line names the option that sets it instead."""

import numpy as np
import pytest

from services.cli.main import _message, _options, build_parser
from services.errors import InputError
from services.structured_light.patterns import generate_sequence
from services.pipeline.reconstruct import reconstruct_capture
from services.simulation.presets import paper_rig

pytestmark = pytest.mark.integration


def test_the_use_case_names_its_parameter_not_a_flag():
    rig = paper_rig()
    sequence, _ = generate_sequence(rig.devices["projector"].width, rig.devices["projector"].height)
    camera = rig.devices["camera"]
    frames = np.zeros((len(sequence.frames), camera.height, camera.width), np.uint8)
    with pytest.raises(InputError) as raised:
        reconstruct_capture(frames=frames, sequence=sequence, rig=rig, tables=None, consistency=2.0)
    assert raised.value.parameter == "consistency"
    assert str(raised.value).startswith("consistency: ") and "--" not in str(raised.value)


def test_the_command_line_names_the_option():
    options = _options(build_parser(["reconstruct"]))
    error = InputError("consistency: the consistency must be between 0 and 1; got 2.0", parameter="consistency")
    assert _message(error, options) == "--consistency: the consistency must be between 0 and 1; got 2.0"
    other = InputError("rig.json: devices.camera.K: focal lengths must be positive")
    assert _message(other, options) == str(other)  # a file's error stays as it is


def test_every_parameter_a_use_case_names_has_an_option():
    options = _options(build_parser())
    assert {name: options.get(name) for name in ("consistency", "max_indirect", "saturation_level", "intrinsics")} \
        == {"consistency": "--consistency", "max_indirect": "--max-indirect", "saturation_level": "--saturation-level",
            "intrinsics": "--intrinsics"}
