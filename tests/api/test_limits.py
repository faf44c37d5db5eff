"""Limits the API keeps: idempotency keys expire after THERMOFIELD_IDEMPOTENCY_TTL_S; uploads are checked
(size, decodable images, device sizes) before anything is stored."""

import time

import pytest

from services.db.models import CalibrationSet, IdempotencyRecord, Job
from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig

PROBLEM = "application/problem+json"


@pytest.fixture
def active_calibration(runtime):
    with runtime.sessions.begin() as session:
        calibration = CalibrationSet(name="rig", station=runtime.settings.station, source="upload", active=True,
                                     rig_sha256=runtime.store.put_bytes(rig_to_json(forging_rig()).encode()))
        session.add(calibration)
    return calibration


def test_an_idempotency_key_expires_after_its_time(client, auth, runtime, active_calibration):
    runtime.settings = runtime.settings.model_copy(update={"idempotency_ttl_s": 1.0})
    headers = {**auth["operate"], "Idempotency-Key": "part-42"}
    first = client.post("/v1/scans", headers=headers, json={"part_id": "42"})
    assert first.status_code == 202
    again = client.post("/v1/scans", headers=headers, json={"part_id": "42"})
    assert again.headers["idempotent-replayed"] == "true" and again.json() == first.json()
    assert client.post("/v1/scans", headers=headers, json={"part_id": "43"}).status_code == 422
    time.sleep(1.2)
    later = client.post("/v1/scans", headers=headers, json={"part_id": "43"})
    assert later.status_code == 202 and "idempotent-replayed" not in later.headers
    assert later.json()["job_id"] != first.json()["job_id"]
    with runtime.sessions() as session:
        assert session.query(IdempotencyRecord).count() == 1 and session.query(Job).count() == 2
