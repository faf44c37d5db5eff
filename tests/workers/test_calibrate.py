"""The calibrate actor on simulated board pairs: the thermal camera re-placed from a wrong pose."""

import json

import cv2
import dramatiq
import numpy as np
import pytest

from services.db.models import CalibrationSet, Job
from services.formats.board import board_to_json, parse_board
from services.formats.rig import parse_rig, rig_to_json
from services.simulation.boards import render_board
from services.simulation.presets import forging_rig
from services.runtime import current_runtime

pytestmark = pytest.mark.integration

BOARD = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0}')


def board_pairs(count: int) -> tuple[list[bytes], list[bytes]]:
    """PNG images of the board in ``count`` poses about 560 mm away, by the true camera and thermal camera."""
    rig = forging_rig()
    centre = BOARD.object_points().mean(axis=0)
    images = {"camera": [], "thermal": []}
    for index in range(count):
        angle = 2 * np.pi * index / count
        board_rotation = cv2.Rodrigues(np.array([0.35 * np.cos(angle), 0.35 * np.sin(angle), 0.1]))[0]
        board_centre = np.array([30 * np.cos(2 * angle), 20 * np.sin(2 * angle), 560 + 30 * np.cos(3 * angle)])
        board_translation = board_centre - board_rotation @ centre
        for name, modality in (("camera", "visible"), ("thermal", "infrared")):
            device = rig.devices[name]
            image = render_board(BOARD, device.K, device.dist, device.R @ board_rotation,
                                 device.R @ board_translation + device.t, device.size,
                                 modality=modality, supersample=1, noise_sigma=1.0,
                                 rng=np.random.default_rng(index))
            images[name].append(cv2.imencode(".png", image)[1].tobytes())
    return images["camera"], images["thermal"]


@pytest.fixture
def wrong_thermal_pose(broker):
    """A calibration set whose thermal camera sits 5, 10 and 15 mm off along x, y, z."""
    runtime = current_runtime()
    rig = json.loads(rig_to_json(forging_rig()))
    thermal = rig["devices"]["thermal"]
    thermal["t"] = [value + 5.0 * (axis + 1) for axis, value in enumerate(thermal["t"])]
    digest = runtime.store.put_bytes(rig_to_json(parse_rig(json.dumps(rig))).encode())
    with runtime.sessions.begin() as session:
        calibration = CalibrationSet(name="drifted", station="station1", rig_sha256=digest, source="upload",
                                     active=True)
        session.add(calibration)
        session.flush()
        return calibration.id


def run_calibration(broker, params: dict) -> Job:
    runtime = current_runtime()
    with runtime.sessions.begin() as session:
        job_id = runtime.tracker.create(session, "calibrate", params).id
    worker = dramatiq.Worker(broker, worker_threads=1, worker_timeout=50)
    worker.start()
    broker.get_actor("calibrate").send(job_id)
    broker.join(runtime.settings.job_queue, timeout=120_000, fail_fast=False)
    worker.stop()
    with runtime.sessions() as session:
        return session.get(Job, job_id)


def stored(images: list[bytes]) -> list[list[str]]:
    return [[current_runtime().store.put_bytes(image), ".png"] for image in images]


def test_calibrate_replaces_the_thermal_camera_where_it_really_is(broker, wrong_thermal_pose):
    camera_images, thermal_images = board_pairs(6)
    store = current_runtime().store
    job = run_calibration(broker, {
        "calibration_set_id": wrong_thermal_pose, "station": "station1", "device": "thermal", "name": "recalibrated",
        "activate": True, "board": store.put_bytes(board_to_json(BOARD).encode()),
        "reference_images": stored(camera_images), "device_images": stored(thermal_images)})
    assert job.status == "succeeded", job.error
    with current_runtime().sessions() as session:
        calibration = session.get(CalibrationSet, job.result["calibration_set_id"])
        assert calibration.active and calibration.source == "calibration"
        assert not session.get(CalibrationSet, wrong_thermal_pose).active
    placed = parse_rig(store.read_bytes(calibration.rig_sha256).decode()).devices["thermal"]
    truth = forging_rig().devices["thermal"]
    assert np.abs(placed.t - truth.t).max() < 0.5  # mm
    angle = np.degrees(np.arccos(np.clip((np.trace(placed.R @ truth.R.T) - 1) / 2, -1, 1)))
    assert angle < 0.05
    assert json.loads(store.read_bytes(job.result["artifacts"]["stereo.json"]))["stereo_rms_px"] < 0.5


def test_images_without_a_board_fail_the_job_at_once_with_the_reason(broker, wrong_thermal_pose):
    blank = [cv2.imencode(".png", np.full((800, 1280), 128, np.uint8))[1].tobytes()] * 3
    blank_thermal = [cv2.imencode(".png", np.full((256, 320), 128, np.uint8))[1].tobytes()] * 3
    store = current_runtime().store
    job = run_calibration(broker, {
        "calibration_set_id": wrong_thermal_pose, "station": "station1", "device": "thermal", "name": "x",
        "activate": False, "board": store.put_bytes(board_to_json(BOARD).encode()),
        "reference_images": stored(blank), "device_images": stored(blank_thermal)})
    assert (job.status, job.attempts) == ("failed", 1)
    assert job.error.startswith("InputError")


@pytest.fixture(scope="module")
def simulated_gateway():
    """The gateway's HTTP API on the simulated station (it holds the board in its poses), on a free port."""
    import socket
    import threading
    import time

    import uvicorn

    from device_gateway.app import create_app
    from device_gateway.drivers.simulated import SimulatedStation
    from device_gateway.station import Station
    from services.structured_light.patterns import generate_sequence

    simulated = SimulatedStation()
    station = Station(simulated.camera, simulated.thermal, simulated.projector, board_holder=simulated)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(create_app(station, *generate_sequence(1280, 800)), host="127.0.0.1",
                                           port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.1)
    assert server.started
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(timeout=30)


# Filming eight views takes most of a minute; the job's database work is the stored-job path every other job
# test runs on both databases, so this one runs on PostgreSQL alone.
@pytest.mark.parametrize("engine", ["postgresql"], indirect=True)
def test_calibration_capture_job_films_the_board_and_replaces_the_thermal_camera(
        broker, wrong_thermal_pose, simulated_gateway):
    runtime = current_runtime()
    runtime.settings.gateway_url = simulated_gateway
    job = run_calibration(broker, {
        "calibration_set_id": wrong_thermal_pose, "station": "station1", "device": "thermal", "name": "captured",
        "activate": True, "board": runtime.store.put_bytes(board_to_json(BOARD).encode()),
        "capture": {"views": 8, "interval_s": 0.0}})
    assert job.status == "succeeded", job.error
    with runtime.sessions() as session:
        calibration = session.get(CalibrationSet, job.result["calibration_set_id"])
        assert calibration.active
    placed = parse_rig(runtime.store.read_bytes(calibration.rig_sha256).decode()).devices["thermal"]
    truth = forging_rig().devices["thermal"]
    assert np.abs(placed.t - truth.t).max() < 0.5  # mm; it started 5..15 mm off
    angle = np.degrees(np.arccos(np.clip((np.trace(placed.R @ truth.R.T) - 1) / 2, -1, 1)))
    assert angle < 0.05
