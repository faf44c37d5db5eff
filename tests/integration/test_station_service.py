"""End to end on the simulated four-head station at 0.3 of its resolution: a station scan through the embedded
service (`thermofield serve`, its simulated gateway filming the heads one after another) and scaled out (the API,
two worker processes and the gateway on PostgreSQL and RabbitMQ). One message per head, joined by a group whose
completion merges, fuses and inspects; a head whose camera is lost mid-capture makes the scan NotDecidable, naming
the head, with everything captured kept."""

import time
import uuid

import httpx
import numpy as np
import pytest

from services.formats.ply import read_cloud
from services.simulation.hot_part import write_shaft_part

pytestmark = pytest.mark.integration

STATION = {"THERMOFIELD_SIMULATED_STATION_HEADS": "4", "THERMOFIELD_SIMULATED_STATION_SCALE": "0.3",
           "THERMOFIELD_CAMERA_EXPOSURE_MODE": "auto"}
HEADS = ["head-1", "head-2", "head-3", "head-4"]


def _part_type(client: httpx.Client, directory) -> str:
    part_file = write_shaft_part(directory)
    created = client.post("/v1/part-types", files={"part": ("part.json", part_file.read_bytes()),
                                                   "mesh": ("shaft.stl", (part_file.parent / "shaft.stl").read_bytes())})
    assert created.status_code == 201, created.text
    return created.json()["part_type_id"]


def _scan(e2e, client: httpx.Client, part_type: str) -> tuple[dict, dict]:
    accepted = client.post("/v1/scans", json={"part_id": "shaft", "part_type_id": part_type})
    assert accepted.status_code == 202, accepted.text
    done = e2e.follow_events(client, accepted.json()["job_id"])[-1][1]
    return done, client.get(f"/v1/scans/{accepted.json()['scan_id']}").json()


def _assert_merged(done: dict, scan: dict) -> None:
    assert done["status"] == "succeeded", done
    station = scan["summary"]["station"]
    assert [head["head"] for head in station["heads"]] == HEADS and station["failed_heads"] == []
    for head in station["heads"]:
        assert head["measured_points"] > 5000 and 0 < head["kept_points"] <= head["measured_points"], head
        assert head["reconstruct_seconds"] > 0 and head["error"] is None
    assert sum(head["kept_points"] for head in station["heads"]) == scan["summary"]["point_count"]
    assert len(station["overlaps"]) >= 4  # each head overlaps its neighbours round the shaft
    assert max(overlap["patch_rms_mm"] for overlap in station["overlaps"]) < 0.1
    assert scan["verdict"] in ("OK", "NotOK", "NotDecidable") and scan["features"]
    assert scan["summary"]["temperature"]["max"] > 900
    assert {f"head {head}" for head in HEADS} <= set(done["result"]["stage_seconds"])
    artifacts = done["result"]["artifacts"]
    for head in HEADS:
        assert {f"heads/{head}/{name}" for name in ("frames.npy", "sequence.json", "cloud.ply")} <= set(artifacts)
    assert {"thermal/thermal-1.npy", "thermal/thermal-2.npy", "field.ply", "field.rrd", "report.json"} <= set(artifacts)


@pytest.fixture(scope="module")
def embedded(tmp_path_factory):
    """`thermofield serve` filming the simulated station, whose head-3 loses its camera in the first capture."""
    from tests.integration.conftest import EndToEnd

    directory = tmp_path_factory.mktemp("station-embedded")
    harness = EndToEnd(directory)
    site = f"it-{uuid.uuid4().hex[:8]}"
    env = {"THERMOFIELD_DATA_DIR": str(directory / "data"), "THERMOFIELD_SITE": site,
           "THERMOFIELD_SIMULATED_LOST_HEAD": "head-3", **STATION}
    port = harness.free_port()
    harness.processes.start("serve", ["serve", "--port", str(port), "--gateway-port", str(harness.free_port()),
                                      "--rerun-port", str(harness.free_port())], env)
    harness.processes.wait_until_healthy(f"http://127.0.0.1:{port}/readyz", "serve", timeout_s=300)
    admin = harness.create_key(env, ["admin"])
    harness.events = harness.mqtt(f"{site}/station1")
    harness.site = site
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {admin}"},
                      timeout=60) as client:
        yield harness, client, directory
    harness.close()


def test_a_lost_head_makes_the_station_scan_not_decidable_and_keeps_what_was_captured(embedded):
    e2e, client, directory = embedded
    part_type = _part_type(client, directory / "part")
    done, scan = _scan(e2e, client, part_type)  # the first capture: head-3's camera is lost half way
    assert done["status"] == "succeeded", done
    assert scan["verdict"] == "NotDecidable" and scan["features"] == []
    reason = done["result"]["inspection_error"]
    assert "head 'head-3'" in reason and "connection lost" in reason and "not judged from the other heads" in reason
    station = scan["summary"]["station"]
    assert station["failed_heads"] == ["head-3"] and station["overlaps"] == []
    assert scan["summary"]["point_count"] == 0 and "field.ply" not in scan["links"]
    # nothing stored is lost: the other heads' frames and clouds, the thermal frames
    artifacts = done["result"]["artifacts"]
    for head in ("head-1", "head-2", "head-4"):
        assert {f"heads/{head}/frames.npy", f"heads/{head}/cloud.ply"} <= set(artifacts), artifacts
        assert [h for h in station["heads"] if h["head"] == head][0]["measured_points"] > 5000
    assert not any(name.startswith("heads/head-3/") for name in artifacts)
    assert {"thermal/thermal-1.npy", "thermal/thermal-2.npy"} <= set(artifacts)
    jobs = client.get("/v1/jobs", params={"limit": 20}).json()
    assert sorted(job["kind"] for job in jobs if job["scan_id"] == scan["scan_id"]) == ["scan", *["scan_head"] * 3]


def test_a_station_scan_through_the_embedded_service_merges_the_heads_and_inspects_all_round(embedded, tmp_path):
    e2e, client, directory = embedded
    part_types = client.get("/v1/part-types").json()
    part_type = part_types[0]["part_type_id"] if part_types else _part_type(client, directory / "part")
    done, scan = _scan(e2e, client, part_type)  # head-3 is back
    _assert_merged(done, scan)
    field = read_cloud_bytes(client.get(scan["links"]["field.ply"]).content, tmp_path)
    assert set(np.unique(field["head"])) == {0, 1, 2, 3}
    recording = client.get(scan["links"]["field.rrd"]).content
    for head in HEADS:
        assert f"world/heads/{head}".encode() in recording
    deadline = time.monotonic() + 10  # MQTT: the scan's topic carries the scan job's states only, the last its summary
    topic = f"{e2e.site}/station1/scans/{scan['scan_id']}"
    while not (states := e2e.events.states(topic)) or states[-1]["status"] != "succeeded":
        assert time.monotonic() < deadline, states
        time.sleep(0.1)
    assert {state["kind"] for state in states} == {"scan"} and "heads" in [state["stage"] for state in states]
    assert states[-1]["summary"]["station"] == scan["summary"]["station"]


def read_cloud_bytes(data: bytes, directory):
    path = directory / "field.ply"
    path.write_bytes(data)
    return read_cloud(path)


@pytest.mark.postgres
@pytest.mark.reliability  # half a minute: in make test-reliability (also in .ci/run), not make test
def test_a_station_scan_scaled_out_runs_its_heads_on_two_workers(e2e, deployment, tmp_path):
    env = deployment | STATION
    api_url = f"http://127.0.0.1:{env['THERMOFIELD_API_PORT']}"
    e2e.processes.start("gateway", ["gateway"], env)
    e2e.processes.start("api", ["api"], env)
    e2e.processes.start("worker", ["worker"], env)
    e2e.processes.wait_until_healthy(f"{env['THERMOFIELD_GATEWAY_URL']}/healthz", "gateway", timeout_s=300)
    e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api")
    admin = e2e.create_key(env, ["admin"])
    from services.formats.rig import rig_to_json
    from services.simulation.presets import station_rig

    with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {admin}"}, timeout=60) as client:
        created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(station_rig(0.3, 4)))},
                              data={"name": "true station", "activate": "true"})
        assert created.status_code == 201, created.text
        part_type = _part_type(client, tmp_path / "part")
        done, scan = _scan(e2e, client, part_type)
        _assert_merged(done, scan)
        head_jobs = [job for job in client.get("/v1/jobs", params={"limit": 20}).json()
                     if job["kind"] == "scan_head" and job["scan_id"] == scan["scan_id"]]
    assert len(head_jobs) == 4 and all(job["status"] == "succeeded" for job in head_jobs)
    assert len({job["worker"] for job in head_jobs}) == 2, head_jobs  # the heads ran in both worker processes
