"""The thermal camera's own radiometric files as stereo-calibration uploads: FLIR R-JPEGs and float TIFFs are
read with the file's parameters and checked before anything is stored; a bad one is a 422 problem naming it."""

import io
import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import tifffile

from services.db.models import Job
from services.formats.rig import Rig, rig_to_json
from services.formats.thermal import read_thermal_frame
from services.pipeline.calibrate import thermal_board_image, uploaded_board_image
from services.simulation.presets import forging_rig

PROBLEM = "application/problem+json"
R_JPEG = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "flir-rjpeg" / "10-ir_fussbodenheizung.jpg"


def _rig_with_a_320x240_thermal_camera() -> Rig:
    rig = forging_rig()
    thermal = rig.devices["thermal"]
    return Rig(devices={**rig.devices, "thermal": replace(thermal, height=240)})


def test_radiometric_thermal_uploads_are_read_and_bad_ones_refused(client, auth, runtime):
    created = client.post("/v1/calibration-sets", headers=auth["admin"],
                          files={"rig": ("rig.json", rig_to_json(_rig_with_a_320x240_thermal_camera()),
                                         "application/json")}, data={"name": "E60 rig", "activate": "true"})
    url = f"/v1/calibration-sets/{created.json()['calibration_set_id']}/stereo"
    camera = forging_rig().devices["camera"]
    camera_image = cv2.imencode(".png", np.zeros((camera.height, camera.width), np.uint8))[1].tobytes()
    board = ("board.json", '{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0}')
    r_jpeg = R_JPEG.read_bytes()
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, read_thermal_frame(R_JPEG))
    float_tiff = buffer.getvalue()

    def post(*device_images):
        files = [("board", board)] + [("reference_images", (f"c{i}.png", camera_image)) for i in range(3)]
        files += [("device_images", image) for image in device_images]
        return client.post(url, headers=auth["admin"], files=files, data={"name": "recalibrated"})

    stored_before = sum(1 for _ in runtime.store.blobs())
    plain = cv2.imencode(".jpg", np.zeros((240, 320, 3), np.uint8))[1].tobytes()
    for bad, message in (((("t2.jpg", plain)), "device_images: 't2.jpg': not a FLIR radiometric JPEG (no FLIR "
                                                "radiometric data; a plain JPEG?)"),
                         ((("t2.jpg", r_jpeg[:len(r_jpeg) // 2])), "device_images: 't2.jpg': FLIR radiometric JPEG "
                                                                   "is truncated"),
                         ((("t2.tiff", float_tiff[:-4000])), "device_images: 't2.tiff': cannot read the thermal "
                                                             "frame")):
        refused = post(("t0.jpg", r_jpeg), ("t1.tiff", float_tiff), bad)
        assert refused.status_code == 422 and refused.headers["content-type"] == PROBLEM, refused.text
        assert refused.json()["detail"].startswith(message) and "\n" not in refused.json()["detail"]
    wrong_size = post(("t0.jpg", r_jpeg), ("t1.jpg", r_jpeg),
                      ("t2.tiff", _float_tiff((256, 320))))
    assert wrong_size.status_code == 422
    assert "t2.tiff': thermal frame is 320x256 but the thermal camera is 320x240" in wrong_size.json()["detail"]
    assert sum(1 for _ in runtime.store.blobs()) == stored_before  # nothing stored from a refused upload

    accepted = post(("t0.jpg", r_jpeg), ("t1.JPEG", r_jpeg), ("t2.tiff", float_tiff))
    assert accepted.status_code == 202, accepted.text
    with runtime.sessions() as session:
        job = session.get(Job, accepted.json()["job_id"])
    suffixes = [suffix for _, suffix in job.params["device_images"]]
    assert suffixes == [".jpg", ".jpeg", ".tiff"]
    # the worker's board images: the file's temperatures stretched, the same from the R-JPEG and its TIFF
    digest_jpeg, digest_tiff = job.params["device_images"][0][0], job.params["device_images"][2][0]
    from_jpeg = uploaded_board_image(runtime.store.read_bytes(digest_jpeg), suffix=".jpg", source="t0")
    from_tiff = uploaded_board_image(runtime.store.read_bytes(digest_tiff), suffix=".tiff", source="t2")
    np.testing.assert_array_equal(from_jpeg, thermal_board_image(read_thermal_frame(R_JPEG)))
    np.testing.assert_array_equal(from_jpeg, from_tiff)
    assert json.loads(runtime.store.read_bytes(job.params["board"]))["square_mm"] == 25.0


def _float_tiff(shape) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, np.full(shape, 20.0, np.float32))
    return buffer.getvalue()
