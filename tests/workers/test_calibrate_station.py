"""The calibrate_station actor on rendered board views of a small simulated station whose stored calibration set
has its heads in the wrong places."""

import json

import cv2
import dramatiq
import numpy as np
import pytest

from services.calibration.station import pose_difference
from services.db.models import CalibrationSet, Job
from services.formats.board import ChessboardSpec, board_to_json
from services.formats.rig import Rig, parse_rig, rig_to_json
from services.runtime import current_runtime
from services.simulation.station_boards import ring_station_rig, station_board_views

pytestmark = pytest.mark.integration
BOARD = ChessboardSpec(type="chessboard", inner_corners=(9, 6), square_mm=30.0)


@pytest.fixture(scope="module")
def station():
    """The true station (a quarter of the cameras' resolution) and its board views as PNG bytes per head."""
    rng = np.random.default_rng(30)
    truth = ring_station_rig(rng, scale=0.25)
    views = station_board_views(truth, BOARD, rng, shared=4, own=4, supersample=1)
    images = {head.name: {f"view{view:03d}.png": cv2.imencode(".png", image)[1].tobytes()
                          for view, image in views.images[head.camera].items()} for head in truth.heads}
    return truth, images


def misplaced(truth: Rig) -> Rig:
    """The station with every head but the first moved as a whole, 20 mm and 1 degree (a world motion
    x -> Q x + s, so that each head's camera and projector keep their pose to each other, as the heads' own
    calibrations give it)."""
    devices, turn = dict(truth.devices), cv2.Rodrigues(np.radians([1.0, 0.0, 0.0]))[0]
    shift = np.full(3, 20.0 / 3**0.5)
    for head in truth.heads[1:]:
        for name in (head.camera, head.projector):
            device = truth.devices[name]
            devices[name] = device.replace(R=device.R @ turn.T, t=device.t - device.R @ turn.T @ shift)
    return Rig(devices, station_heads=truth.station_heads)


def test_calibrate_station_puts_every_head_back_where_it_is(broker, station):
    truth, images = station
    runtime = current_runtime()
    with runtime.sessions.begin() as session:
        calibration = CalibrationSet(name="moved", station="station1", source="upload", active=True,
                                     rig_sha256=runtime.store.put_bytes(rig_to_json(misplaced(truth)).encode()))
        session.add(calibration)
        session.flush()
        calibration_id = calibration.id
    views = {head: [[runtime.store.put_bytes(content), ".png", label] for label, content in files.items()]
             for head, files in images.items()}
    params = {"calibration_set_id": calibration_id, "station": "station1", "name": "station", "world": None,
              "intrinsics": "refined", "activate": True, "board": runtime.store.put_bytes(board_to_json(BOARD).encode()),
              "views": views}
    with runtime.sessions.begin() as session:
        job_id = runtime.tracker.create(session, "calibrate_station", params).id
    worker = dramatiq.Worker(broker, worker_threads=1, worker_timeout=50)
    worker.start()
    broker.get_actor("calibrate_station").send(job_id)
    broker.join(runtime.settings.job_queue, timeout=600_000, fail_fast=False)
    worker.stop()
    with runtime.sessions() as session:
        job = session.get(Job, job_id)
        assert job.status == "succeeded", job.error
        calibration = session.get(CalibrationSet, job.result["calibration_set_id"])
        assert calibration.active and calibration.source == "calibration"
    placed = parse_rig(runtime.store.read_bytes(calibration.rig_sha256).decode())
    assert placed.heads == truth.heads
    for head in truth.heads:  # the first head's camera kept its (true) pose: the world is the truth's
        for name in (head.camera, head.projector):
            error = pose_difference(truth.devices[name].R, truth.devices[name].t, placed.devices[name].R,
                                    placed.devices[name].t)
            assert np.linalg.norm(error[:3]) < 0.25 and np.linalg.norm(error[3:]) < 3.0, (name, error)
    report = json.loads(runtime.store.read_bytes(job.result["artifacts"]["station.json"]))
    assert report["version"] == 1 and len(report["overlaps"]) == 4 and report["overlap_rms_px"] < 0.2
