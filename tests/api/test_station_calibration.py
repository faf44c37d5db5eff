"""POST /v1/calibration-sets/{id}/station: the upload of a station's board views is checked and queued."""

import cv2
import numpy as np

from services.db.models import Job
from services.formats.rig import rig_to_json
from services.simulation.station_boards import ring_station_rig

from .test_api import upload_rig

BOARD = '{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 30.0}'


def test_station_calibration_checks_its_upload_and_queues_a_calibrate_station_job(client, auth, runtime):
    station = ring_station_rig(scale=0.25)
    calibration_id = upload_rig(client, auth["admin"], rig_to_json(station)).json()["calibration_set_id"]
    url = f"/v1/calibration-sets/{calibration_id}/station"
    image = cv2.imencode(".png", np.full((200, 320), 128, np.uint8))[1].tobytes()
    wrong_size = cv2.imencode(".png", np.full((100, 160), 128, np.uint8))[1].tobytes()

    def post(names=("north/v1.png", "east/v1.png"), content=image, **form):
        files = [("board", ("board.json", BOARD))] + [("images", (name, content)) for name in names]
        return client.post(url, headers=auth["admin"], files=files, data={"name": "station", **form})

    stored_before = sum(1 for _ in runtime.store.blobs())
    unknown = post(names=("north/v1.png", "upper/v1.png"))
    assert unknown.status_code == 422 and "'upper/v1.png' must be named HEAD/FILE" in unknown.json()["detail"]
    flat = post(names=("v1.png", "north/v1.png"))
    assert flat.status_code == 422 and "'v1.png'" in flat.json()["detail"]
    small = post(content=wrong_size)
    assert small.status_code == 422 and "north/v1.png" in small.json()["detail"], small.text
    assert sum(1 for _ in runtime.store.blobs()) == stored_before  # nothing stored from a refused upload

    accepted = post(names=("north/v1.png", "east/v1.png", "east/v2.png"), world="east", activate="true")
    assert accepted.status_code == 202 and accepted.headers["location"].startswith("/v1/jobs/")
    with runtime.sessions() as session:
        job = session.get(Job, accepted.json()["job_id"])
    assert job.kind == "calibrate_station" and job.params["world"] == "east" and job.params["activate"]
    assert {head: [label for *_, label in uploads] for head, uploads in job.params["views"].items()} == {
        "north": ["v1.png"], "east": ["v1.png", "v2.png"]}


def test_a_calibration_set_without_heads_is_not_a_station(client, auth):
    calibration_id = upload_rig(client, auth["admin"]).json()["calibration_set_id"]  # the one-head forging rig
    files = [("board", ("board.json", BOARD))] + [("images", (f"head/v{i}.png", b"x")) for i in range(2)]
    refused = client.post(f"/v1/calibration-sets/{calibration_id}/station", headers=auth["admin"], files=files,
                          data={"name": "station"})
    assert refused.status_code == 422 and "is not a station" in refused.json()["detail"]
