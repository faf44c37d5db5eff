"""Property-based tests (Hypothesis) of the public file parsers (rig, board, manifest, part, PLY, thermal
frames): whatever the bytes, a parser either returns its object or raises the documented ``InputError`` --
never another exception."""

from __future__ import annotations

import copy
import json
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
import pytest

from services.errors import InputError
from services.formats.board import parse_board
from services.formats.part import parse_part
from services.formats.ply import read_cloud, write_cloud
from services.formats.rig import parse_rig, rig_to_json
from services.formats.sequence import parse_sequence, sequence_to_json
from services.formats.thermal import read_thermal_frame
from services.simulation.hot_part import write_billet_part
from services.simulation.presets import forging_rig
from services.structured_light.patterns import generate_sequence

pytestmark = pytest.mark.integration

PROPERTY_SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**12, 10**12)
    | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=20),
    lambda children: st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5),
    max_leaves=20,
)
VALID_DOCUMENTS = {
    "rig": json.loads(rig_to_json(forging_rig())),
    "board": {"type": "charuco", "squares": [5, 7], "square_mm": 20, "marker_mm": 15},
    "manifest": json.loads(sequence_to_json(generate_sequence(64, 48)[0])),
}
PARSERS = {"rig": parse_rig, "board": parse_board, "manifest": parse_sequence}


def _leaf_paths(document, prefix=()):
    """Every path (tuple of keys/indices) into ``document``, containers included."""
    yield prefix
    if isinstance(document, dict):
        for key, value in document.items():
            yield from _leaf_paths(value, prefix + (key,))
    elif isinstance(document, list):
        for index, value in enumerate(document):
            yield from _leaf_paths(value, prefix + (index,))


def _replace(document, path, value):
    if not path:
        return value
    replaced = copy.deepcopy(document)
    target = replaced
    for part in path[:-1]:
        target = target[part]
    target[path[-1]] = value
    return replaced


@st.composite
def mutated_documents(draw, kind: str) -> str:
    """A valid document of ``kind`` with one part (a field, list or the whole) replaced by random JSON,
    a key dropped, or its text cut short: close to valid, so that the parser's deeper checks run."""
    document = VALID_DOCUMENTS[kind]
    paths = list(_leaf_paths(document))
    path = draw(st.sampled_from(paths))
    how = draw(st.sampled_from(["replace", "drop", "truncate"]))
    if how == "replace":
        return json.dumps(_replace(document, path, draw(JSON_VALUES)))
    if how == "drop" and path:
        parent = copy.deepcopy(document)
        target = parent
        for part in path[:-1]:
            target = target[part]
        del target[path[-1]]
        return json.dumps(parent)
    text = json.dumps(document)
    return text[: draw(st.integers(0, len(text)))]


def _parses_or_input_error(parse, text: str) -> None:
    try:
        parse(text, "the file")
    except InputError as error:
        assert str(error).startswith("the file"), str(error)


@PROPERTY_SETTINGS
@given(kind=st.sampled_from(sorted(PARSERS)), text=st.text(max_size=200))
def test_json_parsers_take_any_text(kind, text):
    _parses_or_input_error(PARSERS[kind], text)


@PROPERTY_SETTINGS
@given(kind=st.sampled_from(sorted(PARSERS)), value=JSON_VALUES)
def test_json_parsers_take_any_json(kind, value):
    _parses_or_input_error(PARSERS[kind], json.dumps(value))


@PROPERTY_SETTINGS
@given(data=st.data(), kind=st.sampled_from(sorted(PARSERS)))
def test_json_parsers_take_nearly_valid_documents(data, kind):
    _parses_or_input_error(PARSERS[kind], data.draw(mutated_documents(kind)))


def test_the_valid_documents_parse():
    """The seeds of the mutations are valid, so the mutations test the checks near validity."""
    for kind, parse in PARSERS.items():
        parse(json.dumps(VALID_DOCUMENTS[kind]))


def _valid_ply() -> bytes:
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "cloud.ply"
        write_cloud(path, {"x": np.arange(4, dtype=np.float32), "y": np.ones(4, np.float32),
                           "temperature": np.full(4, 800.0, np.float32)})
        return path.read_bytes()


VALID_PLY = _valid_ply()


def _read_file(reader, suffix: str, content: bytes):
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / f"file{suffix}"
        path.write_bytes(content)
        try:
            return reader(path)
        except InputError as error:
            assert str(path) in str(error), str(error)
            return None


@st.composite
def damaged(draw, valid: bytes) -> bytes:
    """``valid`` cut short, with bytes flipped, or with random bytes appended."""
    how = draw(st.sampled_from(["cut", "flip", "append"]))
    if how == "cut":
        return valid[: draw(st.integers(0, len(valid)))]
    if how == "append":
        return valid + draw(st.binary(max_size=64))
    content = bytearray(valid)
    for position in draw(st.lists(st.integers(0, len(valid) - 1), min_size=1, max_size=8)):
        content[position] = draw(st.integers(0, 255))
    return bytes(content)


@PROPERTY_SETTINGS
@given(content=st.binary(max_size=300) | damaged(VALID_PLY))
def test_ply_reader_takes_any_bytes(content):
    cloud = _read_file(read_cloud, ".ply", content)
    if cloud is not None:
        assert all(isinstance(values, np.ndarray) and values.ndim == 1 for values in cloud.values())


def _thermal_samples() -> dict[str, bytes]:
    import cv2
    import tifffile

    samples = {}
    with tempfile.TemporaryDirectory() as directory:
        frame = np.linspace(20, 900, 12 * 16, dtype=np.float32).reshape(12, 16)
        tifffile.imwrite(Path(directory) / "t.tiff", frame)
        np.save(Path(directory) / "t.npy", frame)
        cv2.imwrite(str(Path(directory) / "t.png"), ((frame + 273.15) * 100).astype(np.uint16))
        for suffix in (".tiff", ".npy", ".png"):
            samples[suffix] = (Path(directory) / f"t{suffix}").read_bytes()
    return samples


THERMAL_SAMPLES = _thermal_samples()


@PROPERTY_SETTINGS
@given(data=st.data(), suffix=st.sampled_from(sorted(THERMAL_SAMPLES)))
def test_thermal_frame_reader_takes_any_bytes(data, suffix):
    content = data.draw(st.binary(max_size=300) | damaged(THERMAL_SAMPLES[suffix]))
    temperature = _read_file(lambda path: read_thermal_frame(path, size=(16, 12)), suffix, content)
    if temperature is not None:
        assert temperature.shape == (12, 16) and temperature.dtype == np.float32


@PROPERTY_SETTINGS
@given(dtype=st.sampled_from(["uint8", "int16", "uint16", "int32", "float16", "float32", "float64", "complex64",
                              "bool"]),
       shape=st.lists(st.integers(0, 5), min_size=0, max_size=4),
       value=st.floats(allow_nan=True, allow_infinity=True, width=16))
def test_thermal_frame_reader_takes_any_npy_array(dtype, shape, value):
    array = np.full(shape, value).astype(dtype) if dtype != "bool" else np.zeros(shape, bool)
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "frame.npy"
        np.save(path, array)
        try:
            temperature = read_thermal_frame(path)
        except InputError as error:
            assert str(path) in str(error)
            return
    assert temperature.ndim == 2 and np.isfinite(temperature).any()


def _part_directory() -> Path:
    """A billet's part file with every kind of feature, a custom material and both optional sections, beside
    its nominal mesh: the seed of the part-file mutations (kept for the session)."""
    directory = Path(tempfile.mkdtemp(prefix="thermofield-part-"))
    path = write_billet_part(directory, segments=24)
    part = json.loads(path.read_text())
    part["features"] += [
        {"name": "face_a", "type": "plane", "region": {"min": [-101, -50, -50], "max": [-99, 50, 50]}},
        {"name": "face_b", "type": "plane", "measure": "flatness", "region": {"min": [99, -50, -50],
                                                                             "max": [101, 50, 50]},
         "nominal": 0.0, "tolerance": [0.0, 0.2]},
        {"name": "length", "type": "distance", "between": ["face_a", "face_b"], "nominal": 200.0,
         "tolerance": [-0.5, 0.5]}]
    part["material"] = {"name": "c45", "elongation": [[0, -2e-4], [20, 0], [1100, 0.015]]}
    part["uncertainty"] = {"emissivity": 0.8, "netd_k": 0.1}
    part["segmentation"] = {"min_temperature_c": 250.0, "max_distance_mm": 4.0}
    path.write_text(json.dumps(part))
    return directory


PART_DIRECTORY = _part_directory()
VALID_PART = VALID_DOCUMENTS["part"] = json.loads((PART_DIRECTORY / "part.json").read_text())


def _part_parses_or_input_error(text: str) -> None:
    try:
        part = parse_part(text, "the file", PART_DIRECTORY)
    except InputError as error:
        assert str(error).startswith("the file"), str(error)
        return
    assert len(part.triangles) > 0 and part.material.name


@PROPERTY_SETTINGS
@given(text=st.text(max_size=200) | JSON_VALUES.map(json.dumps))
def test_part_parser_takes_any_text_and_any_json(text):
    _part_parses_or_input_error(text)


@PROPERTY_SETTINGS
@given(data=st.data())
def test_part_parser_takes_nearly_valid_part_files(data):
    _part_parses_or_input_error(data.draw(mutated_documents("part")))


@PROPERTY_SETTINGS
@given(content=st.binary(max_size=300) | damaged((PART_DIRECTORY / "billet.stl").read_bytes()),
       suffix=st.sampled_from([".stl", ".ply", ".obj"]))
def test_part_parser_takes_any_nominal_mesh_bytes(content, suffix):
    with tempfile.TemporaryDirectory() as directory:
        (Path(directory) / f"mesh{suffix}").write_bytes(content)
        try:
            part = parse_part(json.dumps({**VALID_PART, "nominal": f"mesh{suffix}"}), "the file", directory)
        except InputError as error:
            assert str(error).startswith("the file: nominal") and f"mesh{suffix}" in str(error), str(error)
            return
    assert np.isfinite(part.vertices).all() and part.triangles.min() >= 0


def test_the_valid_part_file_parses():
    part = parse_part(json.dumps(VALID_PART), "the file", PART_DIRECTORY)
    assert [feature.name for feature in part.definition.features] == ["body_diameter", "face_a", "face_b", "length"]
