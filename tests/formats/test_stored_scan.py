"""The stored scan's one home: artifact names and encodings, the exposure record."""

import numpy as np
import pytest
from pydantic import ValidationError

from services.formats.stored_scan import (ARTIFACTS, RAW, SERVED, Exposure, exposure_bytes, exposure_from_bytes,
                                          npy_bytes)


def test_the_catalogue_says_which_artifacts_are_raw_served_and_inspected():
    assert RAW == ("frames.npy", "thermal.npy", "sequence.json")
    assert set(SERVED) == set(ARTIFACTS) - {"sequence.json", "exposure.json"}
    assert {name for name, artifact in ARTIFACTS.items() if artifact.inspected} == {"report.json", "deviation.ply"}
    assert SERVED["report.json"].media_type == "application/json"


@pytest.mark.parametrize("array", [np.arange(24, dtype=np.uint16).reshape(2, 3, 4),
                                   np.array([[1.5, np.nan]], dtype=np.float32)])
def test_npy_bytes_round_trip_without_pickles(array):
    import io

    back = np.load(io.BytesIO(npy_bytes(array)), allow_pickle=False)
    assert back.dtype == array.dtype and np.array_equal(back, array, equal_nan=True)


def test_the_exposure_round_trips_and_keeps_what_the_gateway_adds():
    gateway = {"mode": "hdr", "exposures_us": [1000.0, None, 250.0], "saturation_level": 4095.0, "glow_level": 0.12}
    back = exposure_from_bytes(exposure_bytes(gateway))
    assert (back.mode, back.exposures_us, back.saturation_level) == ("hdr", [1000.0, None, 250.0], 4095.0)
    assert back.model_dump()["glow_level"] == 0.12
    assert exposure_from_bytes(None) == Exposure() and Exposure().mode == "fixed"
    with pytest.raises(ValidationError):
        exposure_from_bytes(b'{"exposures_us": "long"}')
