import numpy as np

from api.schemas import FieldSummary
from services.pipeline.summary import field_summary, glow_summary
from services.structured_light.glow import GlowReport

FIELD = {"x": np.array([0.0, 10.0]), "y": np.array([0.0, 5.0]), "z": np.array([600.0, 610.0]),
         "temperature": np.array([1000.0, np.nan])}


def test_glow_summary_says_what_the_glow_did_and_validates_as_the_api_schema():
    report = GlowReport(glowing_fraction=0.12, saturated_fraction=0.1, lost_fraction=0.6, glow_level=0.79,
                        drift=-0.01, hint="use a blue projector and a band-pass filter on the camera")
    glow = glow_summary(report, {"mode": "auto", "exposures_us": [18.2], "saturation_level": 4095})
    assert glow["lost_to_glow"] == 0.7 and glow["exposure_mode"] == "auto" and glow["exposures_us"] == [18.2]
    summary = FieldSummary.model_validate({**field_summary(FIELD), "glow": glow})
    assert summary.glow.hint.startswith("use a blue projector")


def test_a_scan_without_a_glow_measurement_has_no_glow_summary():
    assert glow_summary(None, {}) is None
    assert FieldSummary.model_validate({**field_summary(FIELD), "glow": None}).glow is None
