import io
import json
import re

import cv2
import numpy as np

from services.db.models import CalibrationSet, Job, Scan
from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig

PROBLEM = "application/problem+json"


def upload_rig(client, headers, text=None, name="station rig", activate=True, **extra_headers):
    text = rig_to_json(forging_rig()) if text is None else text
    return client.post("/v1/calibration-sets", headers={**headers, **extra_headers},
                       files={"rig": ("rig.json", text, "application/json")},
                       data={"name": name, "activate": str(activate).lower()})


def test_health_needs_no_key_and_readiness_checks_the_schema(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    from alembic.config import Config
    from alembic.script import ScriptDirectory

    from services.db.engine import MIGRATIONS_DIR

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    head = ScriptDirectory.from_config(config).get_current_head()
    ready = client.get("/readyz").json()
    assert ready["status"] == "ready" and f"schema revision {head})" in ready["checks"]["database"]


def test_without_keys_nothing_but_health_is_served(client):
    for path in ("/v1/scans", "/v1/jobs", "/v1/calibration-sets", "/v1/devices", "/v1/jobs/x"):
        response = client.get(path)
        assert response.status_code == 401, path
        assert response.headers["content-type"] == PROBLEM
        assert response.headers["www-authenticate"] == "Bearer"
    assert client.post("/v1/scans").status_code == 401


def test_unknown_key_and_missing_scope_are_refused(client, auth):
    response = client.get("/v1/scans", headers={"Authorization": "Bearer tf_wrong"})
    assert response.status_code == 401 and "unknown or revoked" in response.json()["detail"]
    response = client.post("/v1/scans", headers=auth["read"])
    assert response.status_code == 403
    body = response.json()
    assert body["type"].endswith("/forbidden") and "'operate'" in body["detail"] and body["status"] == 403


def test_scan_without_active_calibration_is_a_conflict(client, auth):
    response = client.post("/v1/scans", headers=auth["operate"])
    assert response.status_code == 409
    assert response.headers["content-type"] == PROBLEM
    assert "no active calibration set" in response.json()["detail"]


def test_calibration_set_upload_download_activate(client, auth, runtime):
    created = upload_rig(client, auth["admin"], activate=False)
    assert created.status_code == 201, created.text
    first = created.json()
    assert created.headers["location"] == first["links"]["self"] and not first["active"]
    downloaded = client.get(first["links"]["rig"], headers=auth["read"])
    assert json.loads(downloaded.text) == json.loads(rig_to_json(forging_rig()))
    second = upload_rig(client, auth["admin"], name="recalibrated").json()
    assert second["active"]
    activated = client.post(f"/v1/calibration-sets/{first['calibration_set_id']}/activate", headers=auth["admin"])
    assert activated.json()["active"]
    listed = {c["calibration_set_id"]: c["active"]
              for c in client.get("/v1/calibration-sets", headers=auth["read"]).json()}
    assert listed == {first["calibration_set_id"]: True, second["calibration_set_id"]: False}
    assert upload_rig(client, auth["operate"]).status_code == 403


def test_bad_rig_upload_names_the_file_and_field(client, auth):
    rig = json.loads(rig_to_json(forging_rig()))
    rig["devices"]["camera"]["K"][0][0] = -5
    response = upload_rig(client, auth["admin"], text=json.dumps(rig))
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    assert "rig (rig.json): devices.camera.K" in response.json()["detail"]
    assert upload_rig(client, auth["admin"], text="{not json").status_code == 422


def test_validation_errors_are_problems_naming_the_field(client, auth):
    upload_rig(client, auth["admin"])
    response = client.post("/v1/scans", headers=auth["operate"], json={"part_id": 5, "colour": "red"})
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    fields = {error["field"] for error in response.json()["errors"]}
    assert {"body.part_id", "body.colour"} <= fields


def test_scan_is_accepted_with_a_location_and_a_queued_job(client, auth, runtime, job_queue):
    calibration = upload_rig(client, auth["admin"]).json()
    response = client.post("/v1/scans", headers=auth["operate"], json={"part_id": "billet-17"})
    assert response.status_code == 202
    accepted = response.json()
    assert response.headers["location"] == f"/v1/jobs/{accepted['job_id']}"
    assert accepted["links"] == {"job": f"/v1/jobs/{accepted['job_id']}", "scan": f"/v1/scans/{accepted['scan_id']}",
                                 "events": f"/v1/jobs/{accepted['job_id']}/events"}
    # one message for the actor named "scan", sent without the API knowing the actor
    (message,) = [json.loads(data) for data in job_queue.broker.queues[job_queue.queue_name].queue]
    assert (message["actor_name"], message["args"]) == ("scan", [accepted["job_id"]])
    job = client.get(response.headers["location"], headers=auth["read"]).json()
    assert (job["status"], job["kind"], job["scan_id"]) == ("queued", "scan", accepted["scan_id"])
    scan = client.get(f"/v1/scans/{accepted['scan_id']}", headers=auth["read"]).json()
    assert scan["part_id"] == "billet-17" and scan["calibration_set_id"] == calibration["calibration_set_id"]
    assert scan["summary"] is None and scan["status"] == "queued"
    missing = client.get(f"/v1/scans/{accepted['scan_id']}/field.ply", headers=auth["read"])
    assert missing.status_code == 404 and missing.json()["type"].endswith("/not-ready")
    assert client.get("/v1/scans/nope", headers=auth["read"]).status_code == 404
    assert client.get(f"/v1/scans/{accepted['scan_id']}/other.txt", headers=auth["read"]).status_code in (404, 422)


def test_idempotency_key_replays_the_first_answer_and_refuses_another_body(client, auth, runtime):
    upload_rig(client, auth["admin"])
    headers = {**auth["operate"], "Idempotency-Key": "mes-42"}
    first = client.post("/v1/scans", headers=headers, json={"part_id": "a"})
    again = client.post("/v1/scans", headers=headers, json={"part_id": "a"})
    assert first.status_code == again.status_code == 202
    assert again.json() == first.json() and again.headers["location"] == first.headers["location"]
    assert again.headers["idempotent-replayed"] == "true"
    with runtime.sessions() as session:
        assert session.query(Scan).count() == 1 and session.query(Job).count() == 1
    other = client.post("/v1/scans", headers=headers, json={"part_id": "b"})
    assert other.status_code == 422 and other.json()["type"].endswith("/idempotency-key-reused")
    fresh = client.post("/v1/scans", headers={**auth["operate"], "Idempotency-Key": "mes-43"}, json={"part_id": "a"})
    assert fresh.json()["scan_id"] != first.json()["scan_id"]


def test_scan_artifacts_and_summary_are_served_from_the_store(client, auth, runtime):
    upload_rig(client, auth["admin"])
    accepted = client.post("/v1/scans", headers=auth["operate"]).json()
    digest = runtime.store.put_bytes(b"ply bytes")
    buffer = io.BytesIO()
    np.save(buffer, np.arange(2 * 4 * 6, dtype=np.uint8).reshape(2, 4, 6))
    frames = runtime.store.put_bytes(buffer.getvalue())
    summary = {"point_count": 3, "points_with_temperature": 2, "bbox_min": [0, 0, 0], "bbox_max": [1, 1, 1],
               "temperature": {"min": 1, "max": 2, "mean": 1.5, "percentiles": {"p50": 1.5}}}
    with runtime.sessions.begin() as session:
        scan = session.get(Scan, accepted["scan_id"])
        scan.artifacts, scan.summary = {"field.ply": digest, "frames.npy": frames}, summary
    got = client.get(f"/v1/scans/{accepted['scan_id']}", headers=auth["read"]).json()
    assert got["summary"]["temperature"]["mean"] == 1.5
    assert set(got["links"]) >= {"field.ply", "frames", "frames.npy"} and "cloud.ply" not in got["links"]
    assert client.get(got["links"]["field.ply"], headers=auth["read"]).content == b"ply bytes"
    png = client.get(got["links"]["frames"].format(index=1), headers=auth["read"])
    assert png.headers["content-type"] == "image/png"
    decoded = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(decoded, np.arange(24, 48, dtype=np.uint8).reshape(4, 6))
    assert client.get(f"/v1/scans/{accepted['scan_id']}/frames/2.png", headers=auth["read"]).status_code == 404
    assert client.get(f"/v1/scans/{accepted['scan_id']}/thermal/0.tiff", headers=auth["read"]).status_code == 404


def test_job_events_stream_until_the_job_is_done(client, auth, runtime):
    upload_rig(client, auth["admin"])
    job_id = client.post("/v1/scans", headers=auth["operate"]).json()["job_id"]
    runtime.tracker.start(job_id)
    runtime.tracker.succeed(job_id, {"ok": 1})
    with client.stream("GET", f"/v1/jobs/{job_id}/events", headers=auth["read"]) as response:
        assert response.headers["content-type"].startswith("text/event-stream")
        text = "".join(response.iter_text())
    assert "event: done" in text and '"status":"succeeded"' in text.replace(" ", "")
    streamed = json.loads(text.split("event: done", 1)[1].split("data:", 1)[1].splitlines()[0])
    polled = client.get(f"/v1/jobs/{job_id}", headers=auth["read"]).json()
    for moment in ("created_at", "started_at", "finished_at"):  # one spelling of a time, over SSE and GET alike
        assert streamed[moment] == polled[moment] and polled[moment].endswith("Z")


def test_metrics_count_requests_and_jobs(client, auth):
    client.get("/v1/jobs", headers=auth["read"])
    text = client.get("/metrics").text
    assert 'thermofield_http_requests_total{method="GET",operation="list_jobs",status="200"} 1.0' in text
    assert 'thermofield_jobs{status="queued"}' in text


def test_openapi_operation_ids_are_stable_names(client):
    operations = {op["operationId"] for path in client.get("/openapi.json").json()["paths"].values()
                  for op in path.values()}
    assert {"create_scan", "get_scan", "list_scans", "download_scan_artifact", "get_job", "stream_job_events",
            "create_calibration_set", "activate_calibration_set", "download_calibration_set", "list_devices",
            "get_health", "get_readiness", "get_metrics"} <= operations


def test_devices_without_a_gateway_is_a_bad_gateway_problem(client, auth):
    response = client.get("/v1/devices", headers=auth["read"])
    assert response.status_code == 502 and response.headers["content-type"] == PROBLEM
    assert "unreachable" in response.json()["detail"]


def test_scan_jobs_check_their_inputs_and_serve_their_artifacts(client, auth, runtime):
    upload_rig(client, auth["admin"])
    scan_id = client.post("/v1/scans", headers=auth["operate"]).json()["scan_id"]
    not_captured = client.post(f"/v1/scans/{scan_id}/jobs", headers=auth["operate"], json={"kind": "fuse"})
    assert not_captured.status_code == 409 and "no stored capture" in not_captured.json()["detail"]
    with runtime.sessions.begin() as session:
        session.get(Scan, scan_id).artifacts = {"frames.npy": runtime.store.put_bytes(b"x")}
    unknown = client.post(f"/v1/scans/{scan_id}/jobs", headers=auth["operate"], json={"kind": "paint"})
    assert unknown.status_code == 422 and unknown.json()["errors"][0]["field"] == "body.kind"
    bad_cloud = client.post(f"/v1/scans/{scan_id}/jobs", headers=auth["operate"],
                            json={"kind": "fuse", "cloud_job_id": "nope"})
    assert bad_cloud.status_code == 422 and "cloud_job_id" in bad_cloud.json()["detail"]
    accepted = client.post(f"/v1/scans/{scan_id}/jobs", headers=auth["operate"],
                           json={"kind": "register", "model": "affine"})
    assert accepted.status_code == 202
    job_id = accepted.json()["job_id"]
    with runtime.sessions() as session:
        assert session.get(Job, job_id).params == {"scan_id": scan_id, "model": "affine",
                                                   "calibration_set_id": session.get(Scan, scan_id).calibration_set_id}
    assert client.get(f"/v1/jobs/{job_id}/artifacts/overlay.png", headers=auth["read"]).status_code == 404
    runtime.tracker.start(job_id)
    runtime.tracker.succeed(job_id, {"artifacts": {"overlay.png": runtime.store.put_bytes(b"png")}})
    job = client.get(f"/v1/jobs/{job_id}", headers=auth["read"]).json()
    overlay = client.get(job["links"]["overlay.png"], headers=auth["read"])
    assert overlay.content == b"png" and overlay.headers["content-type"] == "image/png"


def test_unknown_routes_and_methods_are_problems_too(client, auth):
    missing = client.get("/v1/nothing", headers=auth["read"])
    assert missing.status_code == 404 and missing.headers["content-type"] == PROBLEM
    assert missing.json()["type"].endswith("/not-found")
    wrong_method = client.delete("/v1/scans", headers=auth["admin"])
    assert wrong_method.status_code == 405 and wrong_method.headers["content-type"] == PROBLEM


def test_stereo_calibration_checks_its_uploads_and_queues_a_calibrate_job(client, auth, runtime):
    calibration_id = upload_rig(client, auth["admin"]).json()["calibration_set_id"]
    url = f"/v1/calibration-sets/{calibration_id}/stereo"
    board = ("board.json", '{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0}')

    rig = forging_rig()
    camera_image = cv2.imencode(".png", np.zeros((rig.devices["camera"].height, rig.devices["camera"].width),
                                                 np.uint8))[1].tobytes()
    thermal_image = cv2.imencode(".png", np.zeros((rig.devices["thermal"].height, rig.devices["thermal"].width),
                                                  np.uint16))[1].tobytes()

    def post(references=3, pairs=3, suffix=".png", board_file=board, device_image=thermal_image, **form):
        files = [("board", board_file)]
        files += [("reference_images", (f"c{i}{suffix}", camera_image)) for i in range(references)]
        files += [("device_images", (f"t{i}{suffix}", device_image)) for i in range(pairs)]
        return client.post(url, headers=auth["admin"], files=files, data={"name": "recalibrated", **form})

    stored_before = sum(1 for _ in runtime.store.blobs())
    for device_image, message in ((b"img", "not a readable PNG"), (camera_image, "but the device filming it is"),
                                  (thermal_image[:200], "not a readable PNG")):
        refused = post(device_image=device_image)
        assert refused.status_code == 422 and message in refused.json()["detail"], refused.text
        assert "t0.png" in refused.json()["detail"] and refused.headers["content-type"] == "application/problem+json"
    assert sum(1 for _ in runtime.store.blobs()) == stored_before  # nothing stored from a refused upload

    assert "same number" in post(pairs=4).json()["detail"]
    too_few = post(references=2, pairs=2)  # fewer than Zhang's method needs: refused by the documented minItems
    assert too_few.status_code == 422 and {error["field"] for error in too_few.json()["errors"]} == {
        "body.reference_images", "body.device_images"}
    assert "not one of" in post(suffix=".gif").json()["detail"]
    wrong_device = post(device="camera")
    assert wrong_device.status_code == 422 and "no thermal device 'camera'" in wrong_device.json()["detail"]
    bad_board = post(board_file=("board.json", '{"type": "chessboard"}'))
    assert bad_board.status_code == 422 and "board (board.json)" in bad_board.json()["detail"]
    accepted = post(activate="true")
    assert accepted.status_code == 202 and accepted.headers["location"].startswith("/v1/jobs/")
    with runtime.sessions() as session:
        job = session.get(Job, accepted.json()["job_id"])
        assert job.kind == "calibrate" and job.params["device"] == "thermal" and job.params["activate"]
        assert len(job.params["reference_images"]) == 3 and job.params["calibration_set_id"] == calibration_id


def test_calibration_capture_checks_its_request_and_queues_a_calibrate_job(client, auth, runtime):
    calibration_id = upload_rig(client, auth["admin"]).json()["calibration_set_id"]
    url = f"/v1/calibration-sets/{calibration_id}/stereo-captures"
    board = {"type": "chessboard", "inner_corners": [9, 6], "square_mm": 30.0}
    request = {"board": board, "views": 10, "interval_s": 1.5, "name": "captured", "activate": True}

    assert client.post(url, headers=auth["operate"], json=request).status_code == 403
    wrong_device = client.post(url, headers=auth["admin"], json={**request, "device": "camera"})
    assert wrong_device.status_code == 422 and "no thermal device 'camera'" in wrong_device.json()["detail"]
    bad_board = client.post(url, headers=auth["admin"], json={**request, "board": {"type": "chessboard"}})
    assert bad_board.status_code == 422 and bad_board.headers["content-type"] == PROBLEM
    assert "square_mm" in bad_board.json()["detail"]
    too_few = client.post(url, headers=auth["admin"], json={**request, "views": 2})
    assert too_few.status_code == 422 and "views" in too_few.json()["detail"]
    accepted = client.post(url, headers=auth["admin"], json=request)
    assert accepted.status_code == 202 and accepted.headers["location"].startswith("/v1/jobs/")
    with runtime.sessions() as session:
        job = session.get(Job, accepted.json()["job_id"])
        assert job.kind == "calibrate" and job.params["capture"] == {"views": 10, "interval_s": 1.5}
        assert job.params["activate"] and job.params["calibration_set_id"] == calibration_id
    assert json.loads(runtime.store.read_bytes(job.params["board"]))["square_mm"] == 30.0


def test_an_artifact_gone_from_the_store_is_a_404_problem_that_says_so(client, auth, runtime):
    upload_rig(client, auth["admin"])
    scan_id = client.post("/v1/scans", headers=auth["operate"]).json()["scan_id"]
    digest = runtime.store.put_bytes(b"a field")
    with runtime.sessions.begin() as session:
        session.get(Scan, scan_id).artifacts = {"field.ply": digest}
    assert client.get(f"/v1/scans/{scan_id}/field.ply", headers=auth["read"]).content == b"a field"
    runtime.store.path(digest).unlink()  # the store lost it (removed by hand, restored from an older backup)
    missing = client.get(f"/v1/scans/{scan_id}/field.ply", headers=auth["read"])
    assert missing.status_code == 404 and missing.headers["content-type"] == PROBLEM
    assert missing.json()["type"].endswith("/artifact-missing") and digest in missing.json()["detail"]
    assert "Traceback" not in missing.text


def test_a_stereo_calibration_from_a_set_without_a_rig_is_a_conflict(client, auth, runtime):
    with runtime.sessions.begin() as session:
        calibration = CalibrationSet(name="in progress", station=runtime.settings.station, source="calibrate")
        session.add(calibration)
        session.flush()
        calibration_id = calibration.id
    refused = client.post(f"/v1/calibration-sets/{calibration_id}/stereo-captures", headers=auth["admin"],
                          json={"name": "again", "board": {"type": "chessboard", "inner_corners": [9, 6],
                                                           "square_mm": 25.0}})
    assert refused.status_code == 409 and refused.json()["type"].endswith("/not-ready"), refused.text


def test_a_body_that_cannot_be_parsed_is_a_422_problem_naming_the_body(client, auth):
    refused = client.post("/v1/scans", headers={**auth["operate"], "Content-Type": "application/json"},
                          content=b"{\"part_id\": \"\xc3\x28\"}")  # not UTF-8
    assert refused.status_code == 422 and refused.headers["content-type"] == PROBLEM
    assert refused.json()["errors"][0]["field"] == "body" and "parsing the body" in refused.json()["detail"]


def test_scans_are_found_by_part_id_and_limited(client, auth, runtime):
    upload_rig(client, auth["admin"])
    made = [client.post("/v1/scans", headers=auth["operate"], json={"part_id": part}).json()["scan_id"]
            for part in ("a", "b", "a", "c")]
    listed = client.get("/v1/scans", headers=auth["read"]).json()
    assert [scan["scan_id"] for scan in listed] == made[::-1]
    by_part = client.get("/v1/scans", params={"part_id": "a"}, headers=auth["read"]).json()
    assert [scan["scan_id"] for scan in by_part] == [made[2], made[0]]
    assert [s["scan_id"] for s in client.get("/v1/scans?limit=2", headers=auth["read"]).json()] == made[:1:-1]
    assert client.get("/v1/scans", params={"part_id": "zzz"}, headers=auth["read"]).json() == []
    bad = client.get("/v1/scans?limit=0", headers=auth["read"])
    assert bad.status_code == 422 and bad.headers["content-type"] == "application/problem+json"


def test_a_report_that_will_never_come_is_not_announced_as_not_ready(client, auth, runtime):
    upload_rig(client, auth["admin"])
    accepted = client.post("/v1/scans", headers=auth["operate"]).json()
    scan_url = f"/v1/scans/{accepted['scan_id']}"
    pending = client.get(f"{scan_url}/field.ply", headers=auth["read"]).json()
    assert pending["type"].endswith("/not-ready") and "is queued" in pending["detail"]
    never = client.get(f"{scan_url}/report.json", headers=auth["read"])  # no part type: no inspection, ever
    assert never.status_code == 404 and never.json()["type"].endswith("/not-found")
    assert "will have none" in never.json()["detail"] and "not inspected" in never.json()["detail"]
    runtime.tracker.start(accepted["job_id"])
    runtime.tracker.fail(accepted["job_id"], "RuntimeError: the camera was lost", will_retry=False)
    failed = client.get(f"{scan_url}/field.ply", headers=auth["read"]).json()
    assert failed["type"].endswith("/not-found") and "has failed" in failed["detail"]


def test_a_json_body_without_content_type_is_refused_for_what_it_lacks(client, auth):
    upload_rig(client, auth["admin"])
    refused = client.post("/v1/scans", headers={**auth["operate"], "Content-Type": ""}, content=b'{"part_id": "a"}')
    assert refused.status_code == 415 and refused.headers["content-type"] == PROBLEM, refused.text
    assert "Content-Type: application/json" in refused.json()["detail"]


def test_the_api_docs_need_no_internet(client):
    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        sources = re.findall(r'(?:src|href)="([^"]+)"', html)
        assert sources and all(source.startswith("/docs-assets/") or source == "/openapi.json" for source in sources)
        assert "https://" not in html, page  # no CDN, no web font
        for source in sources:
            if source.startswith("/docs-assets/"):
                asset = client.get(source)
                assert asset.status_code == 200 and len(asset.content) > 1000, source
