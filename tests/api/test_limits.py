"""Limits the API keeps: idempotency keys expire after THERMOFIELD_IDEMPOTENCY_TTL_S; uploads are checked
(size, decodable images, device sizes) before anything is stored."""

import json
import time

import pytest

from services.db.models import ApiKey, CalibrationSet, IdempotencyRecord, Job
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
    time.sleep(1.2)  # the test: the key's 1 s lifetime passes
    later = client.post("/v1/scans", headers=headers, json={"part_id": "43"})
    assert later.status_code == 202 and "idempotent-replayed" not in later.headers
    assert later.json()["job_id"] != first.json()["job_id"]
    with runtime.sessions() as session:
        assert session.query(IdempotencyRecord).count() == 1 and session.query(Job).count() == 2


def test_artifact_names_never_reach_outside_the_store(client, auth, runtime):
    with runtime.sessions.begin() as session:
        job = Job(kind="register", status="succeeded", params={},
                  result={"artifacts": {"overlay.png": runtime.store.put_bytes(b"png")}})
        session.add(job)
    outside = runtime.store.root.parent / "secret.txt"
    outside.write_text("not an artifact")
    for name in ("../secret.txt", "..%2F..%2Fsecret.txt", "%2e%2e%2fsecret.txt", "overlay.png%00", "/etc/passwd"):
        response = client.get(f"/v1/jobs/{job.id}/artifacts/{name}", headers=auth["read"])
        assert response.status_code == 404, (name, response.status_code)
        assert "not an artifact" not in response.text
    assert client.get(f"/v1/jobs/{job.id}/artifacts/overlay.png", headers=auth["read"]).content == b"png"
    for digest in ("../secret.txt", "../" * 3 + "etc/passwd", "A" * 64, "0" * 63):
        with pytest.raises(KeyError):
            runtime.store.path(digest)


def test_oversized_uploads_are_refused_before_anything_is_stored(client, auth, runtime):
    runtime.settings = runtime.settings.model_copy(update={"max_image_bytes": 1000})
    stored = sum(1 for _ in runtime.store.blobs())
    huge_rig = client.post("/v1/calibration-sets", headers=auth["admin"], data={"name": "x"},
                           files={"rig": ("rig.json", b" " * (2 << 20))})
    assert huge_rig.status_code == 413 and huge_rig.headers["content-type"] == PROBLEM
    assert "rig" in huge_rig.json()["detail"]
    assert sum(1 for _ in runtime.store.blobs()) == stored


def test_the_job_queue_has_a_bound_beyond_which_new_jobs_get_503(client, auth, runtime, active_calibration):
    runtime.settings = runtime.settings.model_copy(update={"job_queue_bound": 3})
    accepted = [client.post("/v1/scans", headers=auth["operate"]) for _ in range(3)]
    assert [response.status_code for response in accepted] == [202] * 3
    refused = client.post("/v1/scans", headers={**auth["operate"], "Idempotency-Key": "full"})
    assert refused.status_code == 503 and refused.headers["content-type"] == PROBLEM
    assert refused.json()["type"].endswith("/queue-full") and "3 jobs" in refused.json()["detail"]
    assert int(refused.headers["retry-after"]) > 0
    with runtime.sessions.begin() as session:  # one job starts running: there is room again
        session.get(Job, accepted[0].json()["job_id"]).status = "running"
    retried = client.post("/v1/scans", headers={**auth["operate"], "Idempotency-Key": "full"})
    assert retried.status_code == 202  # the refusal was not stored as the key's answer
    with runtime.sessions() as session:
        assert session.query(Job).filter(Job.status == "queued").count() == 3 and session.query(Job).count() == 4
    operation = client.get("/openapi.json").json()["paths"]["/v1/scans"]["post"]
    assert "application/problem+json" in operation["responses"]["503"]["content"]
    assert "queue is full" in operation["responses"]["503"]["description"]


def _chunks(body: bytes, size: int = 64 << 10):
    """A body sent in chunks with no Content-Length (``Transfer-Encoding: chunked``)."""
    for start in range(0, len(body), size):
        yield body[start:start + size]


def _assert_payload_too_large(response, limit: int) -> None:
    assert response.status_code == 413, response.text
    assert response.headers["content-type"] == PROBLEM
    assert response.json()["type"].endswith("/payload-too-large") and f"{limit} bytes" in response.json()["detail"]


def test_json_bodies_over_the_limit_are_refused_before_they_are_read_whole(client, auth, runtime,
                                                                           active_calibration):
    runtime.settings = runtime.settings.model_copy(update={"max_body_bytes": 4096})
    padded = json.dumps({"part_id": "42", "padding": " " * 8192}).encode()
    json_type = {"Content-Type": "application/json"}
    for path, headers in (("/v1/scans", auth["operate"]), ("/v1/api-keys", auth["admin"]),
                          (f"/v1/calibration-sets/{active_calibration.id}/stereo-captures", auth["admin"])):
        declared = client.post(path, headers={**headers, **json_type}, content=padded)
        _assert_payload_too_large(declared, 4096)
        streamed = client.post(path, headers={**headers, **json_type}, content=_chunks(padded, 1024))
        assert "content-length" not in streamed.request.headers and streamed.request.headers["transfer-encoding"] == \
            "chunked"
        _assert_payload_too_large(streamed, 4096)
    with runtime.sessions() as session:
        assert session.query(Job).count() == 0 and session.query(ApiKey).count() == 3  # the fixture's keys alone
    small = client.post("/v1/scans", headers={**auth["operate"], **json_type},
                        content=_chunks(json.dumps({"part_id": "42"}).encode(), 4))
    assert small.status_code == 202, small.text  # chunked bodies within the limit go through
    operation = client.get("/openapi.json").json()["paths"]["/v1/scans"]["post"]
    assert PROBLEM in operation["responses"]["413"]["content"]


def test_multipart_uploads_over_the_limit_are_refused_declared_or_streamed(client, auth, runtime):
    runtime.settings = runtime.settings.model_copy(update={"max_upload_bytes": 64 << 10})
    stored = sum(1 for _ in runtime.store.blobs())
    rig = rig_to_json(forging_rig()).encode()
    request = client.build_request("POST", "/v1/calibration-sets", headers=auth["admin"], data={"name": "big"},
                                   files={"rig": ("rig.json", rig + b" " * (128 << 10))})
    body, content_type = request.read(), request.headers["content-type"]
    declared = client.post("/v1/calibration-sets", headers={**auth["admin"], "Content-Type": content_type},
                           content=body)
    _assert_payload_too_large(declared, 64 << 10)
    streamed = client.post("/v1/calibration-sets", headers={**auth["admin"], "Content-Type": content_type},
                           content=_chunks(body))
    assert "content-length" not in streamed.request.headers
    _assert_payload_too_large(streamed, 64 << 10)
    assert sum(1 for _ in runtime.store.blobs()) == stored and not list((runtime.store.root / "incoming").glob("*"))
    with runtime.sessions() as session:
        assert session.query(CalibrationSet).count() == 0
    accepted = client.post("/v1/calibration-sets", headers=auth["admin"], data={"name": "small"},
                           files={"rig": ("rig.json", rig)})
    assert len(rig) < 64 << 10 and accepted.status_code == 201, accepted.text
