import json

import numpy as np
import pytest

from services.errors import InputError
from services.formats.registration import load_registration, parse_registration, registration_json, save_registration
from services.registration.register import Registration


def _result() -> Registration:
    matrix = np.array([[3.0, -0.1, 40.0], [0.1, 3.0, 25.0], [0.0, 0.0, 1.0]])
    return Registration("similarity", matrix, 0.95, 1.21, 32, 2.0)


def test_round_trip_keeps_every_field(tmp_path):
    path = tmp_path / "REG.json"
    save_registration(_result(), path)
    loaded = load_registration(path)
    assert loaded.model == "similarity" and loaded.bins == 32 and loaded.log_base == 2.0
    assert loaded.mi == 0.95 and loaded.nmi == 1.21
    np.testing.assert_array_equal(loaded.matrix_array, _result().matrix)
    assert set(json.loads(path.read_text())) == {"model", "matrix", "mi", "nmi", "bins", "log_base"}
    assert not list(tmp_path.glob("*.part"))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"model": "elastic"}, "model"),
        ({"matrix": [[1, 0], [0, 1]]}, "matrix"),
        ({"matrix": [[0, 0, 0], [0, 0, 0], [0, 0, 1]]}, "invertible"),
        ({"bins": 1}, "bins"),
        ({"log_base": 1.0}, "log base must not be 1"),
        ({"extra": 3}, "extra"),
    ],
)
def test_bad_content_names_the_file_and_field(change, message):
    document = json.loads(registration_json(_result())) | change
    with pytest.raises(InputError, match=message) as raised:
        parse_registration(json.dumps(document), "REG.json")
    assert "REG.json" in str(raised.value)


def test_unreadable_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="cannot read the registration file"):
        load_registration(tmp_path / "absent.json")


def test_writing_does_not_import_pydantic():
    """The register command writes REG.json; only reading validates with pydantic."""
    import subprocess
    import sys

    code = ("import sys; from services.formats.registration import save_registration; "
            "print('pydantic' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"
