"""Use case: a structured-light capture to a point cloud, every input check made here once."""

from __future__ import annotations

import numpy as np

from services.errors import InputError
from services.formats.rig import Rig
from services.formats.sequence import Sequence
from services.pipeline.tables import TriangulationTables
from services.structured_light.decode import decode
from services.structured_light.reconstruct import Reconstruction, coded_axis, reconstruct_scan
from services.structured_light import defaults


def reconstruct_capture(*, frames: np.ndarray, sequence: Sequence, rig: Rig, tables: TriangulationTables,
                        camera: str | None = None, projector: str | None = None,
                        saturation_level: float | None = None, max_indirect: float = defaults.MAX_INDIRECT,
                        consistency: float = defaults.CONSISTENCY, source: str = "the capture") -> Reconstruction:
    """Decode and triangulate a capture with the rig's camera and projector.

    Parameters
    ----------
    frames : (F, H, W) uint8 or uint16 array
        The camera frames in the order of ``sequence``.
    sequence : Sequence
        What each frame encodes (the manifest).
    rig : Rig
        The calibration; ``camera`` and ``projector`` name its devices (default: the only ones).
    tables : TriangulationTables
        Where the calibration's triangulation table is kept between calls.
    saturation_level : float, optional
        The grey level at which the camera saturates (4095 for 12-bit frames in 16-bit files); default the
        frames' dtype maximum.
    max_indirect, consistency : float
        Rejection of inter-reflections (see :func:`services.structured_light.reconstruct.reconstruct_scan`).
    source : str
        Names the capture in error messages (a directory, an artifact).

    Returns
    -------
    Reconstruction
        The cloud, and what a hot part's glow did (for sequences closed by a black frame).

    Raises
    ------
    InputError
        When the manifest's projector or the frames do not match the rig, the saturation level is
        impossible, no point is reconstructed, or a glowing part is measured on less than 1 % of its pixels
        (:meth:`services.structured_light.glow.GlowReport.refusal`).
    """
    _, camera_model = rig.device(camera, "camera")
    _, projector_model = rig.device(projector, "projector")
    if (sequence.projector.width, sequence.projector.height) != projector_model.size:
        raise InputError(
            f"{source}: the manifest is for a {sequence.projector.width}x{sequence.projector.height} projector "
            f"but the rig's projector is {projector_model.width}x{projector_model.height}")
    if frames.ndim != 3 or (frames.shape[2], frames.shape[1]) != camera_model.size:
        shape = f"{frames.shape[2]}x{frames.shape[1]}" if frames.ndim == 3 else f"of shape {frames.shape}"
        raise InputError(f"{source}: frames are {shape} but the rig's camera is "
                         f"{camera_model.width}x{camera_model.height}")
    if saturation_level is not None and not 0 < saturation_level <= np.iinfo(frames.dtype).max:
        raise InputError(f"saturation_level: the saturation level must be in (0, {np.iinfo(frames.dtype).max}] "
                         f"for {frames.dtype} frames; got {saturation_level:g}", parameter="saturation_level")
    if not max_indirect > 0:
        raise InputError(f"max_indirect: the maximum indirect ratio must be positive; got {max_indirect}",
                         parameter="max_indirect")
    if not 0 <= consistency <= 1:
        raise InputError(f"consistency: the consistency must be between 0 and 1; got {consistency}",
                         parameter="consistency")
    try:
        axis = coded_axis(sequence.coded_axes, camera_model, projector_model)
    except ValueError as error:
        raise InputError(f"{source}: {error}") from None
    table = tables.get(camera_model, projector_model, axis)
    reconstruction = reconstruct_scan(frames, sequence, camera_model, projector_model, table=table,
                                      saturation_level=saturation_level, max_indirect=max_indirect,
                                      consistency=consistency)
    refusal = None if reconstruction.glow is None else reconstruction.glow.refusal()
    if refusal is not None:
        raise InputError(f"{source}: {refusal}")
    if len(reconstruction.cloud) == 0:
        counts = np.bincount(decode(frames, sequence).rejection.ravel())
        reasons = ", ".join(f"code {code}: {count} px" for code, count in enumerate(counts) if count)
        raise InputError(
            f"{source}: no point could be reconstructed (rejected pixels by reason {reasons}; see "
            "docs/sequence-manifest.md for the codes); check exposure, the manifest and the rig")
    return reconstruction
