"""The baseline of benchmarks/bench_commands.py: a plain numpy Gray-code + phase-shift decoder, as a script.

It does the work of ``thermofield reconstruct`` the plain way, in its own process and with nothing of
thermofield: read the manifest, the rig and the frames (OpenCV), threshold each Gray plane against its
inverse, convert Gray to binary, take the wrapped phase of the N-step phase shift and unwrap it with the
Gray-code stripe, triangulate every decoded pixel against its projector column as a pinhole ray-plane
intersection (lens distortion ignored), and write the points as a binary PLY.

Usage: python benchmarks/numpy_decoder.py RIG.json CAPTURE_DIR OUT.ply
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np


def decode(frames: np.ndarray, manifest: dict) -> np.ndarray:
    """The projector column of every camera pixel, NaN where the pixel is in shadow."""
    kinds = [frame["kind"] for frame in manifest["frames"]]
    f = frames.astype(np.float32)
    valid = (f[kinds.index("white")] - f[kinds.index("black")]) > 10
    planes = sorted(((frame["bit"], index) for index, frame in enumerate(manifest["frames"])
                     if frame["kind"] == "gray" and frame.get("axis", "x") == "x" and not frame.get("inverted")),
                    reverse=True)
    inverse = {frame["bit"]: index for index, frame in enumerate(manifest["frames"])
               if frame["kind"] == "gray" and frame.get("axis", "x") == "x" and frame.get("inverted")}
    binary = np.zeros(frames.shape[1:], np.int32)
    bit_value = np.zeros(frames.shape[1:], np.int32)
    for bit, index in planes:
        bit_value ^= (f[index] > f[inverse[bit]]).astype(np.int32)
        binary = (binary << 1) | bit_value
    finest = planes[-1][0]
    gray_estimate = (binary + 0.5) * (1 << finest) - 0.5
    phases = [(index, frame) for index, frame in enumerate(manifest["frames"])
              if frame["kind"] == "phase" and frame.get("axis", "x") == "x"]
    period = min(frame["period"] for _, frame in phases)
    finest_phase = [(index, frame) for index, frame in phases if frame["period"] == period]
    shifts = np.array([2 * np.pi * frame["step"] / frame["steps"] for _, frame in finest_phase], np.float32)
    stack = f[[index for index, _ in finest_phase]]
    sine = np.tensordot(np.sin(shifts), stack, axes=1)
    cosine = np.tensordot(np.cos(shifts), stack, axes=1)
    wrapped = np.mod(np.arctan2(sine, cosine), 2 * np.pi) * (period / (2 * np.pi))
    column = wrapped + period * np.round((gray_estimate - wrapped) / period)
    return np.where(valid, column, np.nan).astype(np.float32)


def triangulate(column: np.ndarray, camera: dict, projector: dict) -> np.ndarray:
    """World points of the decoded pixels: camera rays meet the projector column's plane (pinhole)."""
    K, R, t = (np.array(camera[name], np.float64) for name in ("K", "R", "t"))
    Kp, Rp, tp = (np.array(projector[name], np.float64) for name in ("K", "R", "t"))
    v, u = np.nonzero(np.isfinite(column))
    c = column[v, u].astype(np.float64)
    rays = np.linalg.solve(K, np.stack([u, v, np.ones_like(u)]).astype(np.float64))  # camera frame
    directions = R.T @ rays  # world frame
    centre = -R.T @ t
    # projector column c is the plane x - (c - cx)/fx z = 0 of the projector frame, X_p = Rp X + tp
    normal_projector = np.stack([np.ones_like(c), np.zeros_like(c), -(c - Kp[0, 2]) / Kp[0, 0]])
    normal_world = Rp.T @ normal_projector
    origin_projector = Rp @ centre + tp
    s = -(normal_projector * origin_projector[:, None]).sum(axis=0) / (normal_world * directions).sum(axis=0)
    return (centre[:, None] + s * directions).T.astype(np.float32)


def write_ply(path: Path, points: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    path.write_bytes(header.encode() + np.ascontiguousarray(points, "<f4").tobytes())


def main(rig_path: str, capture: str, out: str) -> None:
    rig = json.loads(Path(rig_path).read_text())["devices"]
    camera = next(device for device in rig.values() if device["kind"] == "camera")
    projector = next(device for device in rig.values() if device["kind"] == "projector")
    manifest = json.loads((Path(capture) / "sequence.json").read_text())
    frames = np.stack([cv2.imread(str(Path(capture) / frame["file"]), cv2.IMREAD_UNCHANGED)
                       for frame in manifest["frames"]])
    points = triangulate(decode(frames, manifest), camera, projector)
    write_ply(Path(out), points)
    print(f"{out}: {len(points)} points")


if __name__ == "__main__":
    main(*sys.argv[1:4])
