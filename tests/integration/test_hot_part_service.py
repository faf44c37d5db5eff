"""End to end over HTTP on a glowing part: `thermofield serve` with its simulated gateway pointed at the
hot-part scene (THERMOFIELD_SIMULATED_SCENE), the hot-part sequence and automatic exposure; the scan
summary, the job's result and the MQTT scan state say what the glow did, and the field is checked
against the simulator's ground truth."""

import time
import uuid

import httpx
import numpy as np
import pytest

from services.formats.ply import read_cloud
from services.geometry.camera import pixel_rays
from services.simulation.presets import forging_rig, hot_optics, hot_part_scene
from services.simulation.raycast import cast_rays

pytestmark = pytest.mark.integration

PART_SURFACES = (0, 1)  # billet and dome; 2 is the cool fixture plate


def test_a_scan_of_a_glowing_part_reports_the_glow_and_measures_the_part(e2e, tmp_path):
    scene = hot_part_scene(1000.0, hot_optics("white"))  # unfiltered white light: the glow is 10x the pattern
    scene_file = tmp_path / "hot-part.json"
    scene_file.write_text(scene.model_dump_json())
    site = f"it-{uuid.uuid4().hex[:8]}"
    env = {"THERMOFIELD_DATA_DIR": str(tmp_path / "data"), "THERMOFIELD_SITE": site,
           "THERMOFIELD_SIMULATED_SCENE": str(scene_file), "THERMOFIELD_HOT_PART_SEQUENCE": "true",
           "THERMOFIELD_CAMERA_EXPOSURE_MODE": "auto"}
    port = e2e.free_port()
    e2e.processes.start("serve", ["serve", "--port", str(port), "--gateway-port", str(e2e.free_port()),
                                  "--rerun-port", str(e2e.free_port()), "--rerun-web-port", str(e2e.free_port())], env)
    e2e.processes.wait_until_healthy(f"http://127.0.0.1:{port}/readyz", "serve")
    admin = e2e.create_key(env, ["admin"])
    events = e2e.mqtt(f"{site}/station1")

    with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {admin}"},
                      timeout=30) as client:
        accepted = client.post("/v1/scans", json={"part_id": "hot-billet"})
        assert accepted.status_code == 202, accepted.text
        scan_id, job_id = accepted.json()["scan_id"], accepted.json()["job_id"]
        done = e2e.follow_events(client, job_id)[-1][1]
        assert done["status"] == "succeeded", done
        scan = client.get(f"/v1/scans/{scan_id}").json()
        (tmp_path / "field.ply").write_bytes(client.get(scan["links"]["field.ply"]).content)

    glow = scan["summary"]["glow"]
    assert glow["exposure_mode"] == "auto" and len(glow["exposures_us"]) == 1
    assert 0.5 < glow["glow_level"] < 0.95  # metered: the glow fills most of the range, below saturation
    assert glow["glowing_fraction"] > 0.1 and glow["saturated_fraction"] == 0.0
    assert glow["lost_to_glow"] == glow["saturated_fraction"] + glow["lost_fraction"]
    assert glow["lost_fraction"] > 0.05 and "blue projector and a band-pass filter" in glow["hint"]
    assert abs(glow["drift"]) < 0.005  # the scene's part does not cool
    assert done["result"]["glow"] == glow
    deadline = time.monotonic() + 10
    while not (states := events.states(f"{site}/station1/scans/{scan_id}")) or states[-1]["status"] != "succeeded":
        assert time.monotonic() < deadline, states
        time.sleep(0.1)
    assert states[-1]["summary"]["glow"] == glow

    field = read_cloud(tmp_path / "field.ply")
    camera = forging_rig().devices["camera"]
    pixels = np.column_stack([field["u"], field["v"]]).astype(np.float64)
    origin, directions = pixel_rays(pixels, camera.K, camera.dist, camera.R, camera.t)
    hits = cast_rays(scene, origin, directions)
    points = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float64)
    on_part = np.isin(hits.surface, PART_SURFACES)
    error = np.linalg.norm(points[on_part] - hits.points[on_part], axis=1)
    assert on_part.sum() > 50_000  # most of the glowing billet and dome (about 110,000 lit pixels)
    assert np.median(error) < 0.1
    assert np.mean(error > 1.0) <= 0.005
