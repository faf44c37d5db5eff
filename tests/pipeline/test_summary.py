import numpy as np

from services.formats.stored_scan import FieldSummary
from services.pipeline.summary import field_summary, glow_summary
from services.structured_light.glow import GlowReport

FIELD = {"x": np.array([0.0, 10.0]), "y": np.array([0.0, 5.0]), "z": np.array([600.0, 610.0]),
         "temperature": np.array([1000.0, np.nan])}


def test_glow_summary_says_what_the_glow_did_and_validates_as_the_api_schema():
    report = GlowReport(glowing_fraction=0.12, saturated_fraction=0.1, lost_fraction=0.6, glow_level=0.79,
                        drift=-0.01, hint="use a blue projector and a band-pass filter on the camera")
    glow = glow_summary(report, {"mode": "auto", "exposures_us": [18.2], "saturation_level": 4095})
    assert glow.lost_to_glow == 0.7 and glow.exposure_mode == "auto" and glow.exposures_us == [18.2]
    # what the job stores (JSON) is what the API reads back
    stored = field_summary(FIELD).model_copy(update={"glow": glow}).model_dump(mode="json")
    summary = FieldSummary.model_validate(stored)
    assert summary.glow.hint.startswith("use a blue projector") and summary.temperature.max == 1000.0


def test_a_scan_without_a_glow_measurement_has_no_glow_summary():
    assert glow_summary(None, {}) is None
    assert field_summary(FIELD).glow is None
