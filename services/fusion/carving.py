"""The space a measuring camera could not see into, as occluders for the thermal views' z-buffers.

A cloud's z-buffer in a thermal view (:mod:`services.fusion.visibility`) holds the surfaces the structured light
reconstructed. The thermal camera also sees surfaces that it did not reconstruct: a part's flanks that face away
from the camera or lie in the projector's shadow. A wall point behind such a flank reads the part's temperature,
because no point of the cloud stands between it and the thermal camera. What the measuring camera tells is where
space is *free*: along each pixel's ray, up to the surface it measured there. Everything behind a measured surface
is unknown, and may hold the unseen surface. A thermal ray to a measured point that passes through unknown space
cannot be trusted, and it must cross the unknown region's boundary to do so: the measured surface itself (already
in the z-buffer) or the "skirts" that join a near surface to a farther one at a depth jump of the camera's view,
along the camera's rays. This module builds those skirts, so that the thermal z-buffer can draw them as occluders.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.camera import normalized_coordinates
from services.geometry.camera_model import CameraModel
from services.geometry.distortion import distorted_pixels, opencv_distortion_terms
from services.geometry.rigid import rigid_transform
from services.fusion.visibility import nearest_pixel_index, splat_nearest

DEFAULT_JUMP_MM = 4.0
"""The smallest depth jump between neighbouring pixels that is a discontinuity, not a steep surface (twice the
fusion's depth tolerance); see :func:`skirt_segments` for the slope term."""
JUMP_SLOPE = 4.0
"""tan of the steepest surface the camera measures (76 degrees): neighbouring pixels on one surface differ in
depth by at most this many pixel footprints."""
DEFAULT_HOLE_REACH_PX = 16
"""How far (pixels) from a pixel without a point the depths around it are taken to bound what the hole hides."""
MAX_SAMPLES_PER_SEGMENT = 2048
"""A bound on one skirt's samples in a thermal view (a skirt seen end-on from behind the camera)."""
PROJECTOR_GAP_PX = 2
"""The gaps between the camera's points in a finer projector's depth map that its nearest depth fills."""


@dataclass(frozen=True)
class Witness:
    """A device that saw the cloud's points: its model and the rows of the cloud it saw (``None``: all).

    A camera's rays are free up to the points it measured, and so are a projector's up to the points it lit
    (a structured-light point is lit by the projector and seen by the camera). ``skirts``: whether the space
    behind its depth map bounds what the fusion trusts (the camera's); a projector only carves it (the points
    it lit but the camera did not see are not in the cloud, so its depth map's holes tell nothing). ``pixels``
    (len(rows), 2): the (u, v) at which it measured each of its rows, when the cloud says (a reconstruction's
    ``u, v``), so that they need not be projected again."""

    camera: CameraModel
    rows: np.ndarray | None = None
    skirts: bool = True
    pixels: np.ndarray | None = None


@dataclass(frozen=True)
class UnseenSpace:
    """The space the witnesses could not see into: its skirts, (M, 2, 3) world segments, and the index of the
    witness each comes from (M,); each witness's model and depth map (its z-buffer of the cloud, +inf where no
    point fell), to carve a skirt by the other witnesses; the smooth surface each cloud point lies on (N,),
    numbered across the witnesses (-1 where none), and its witness, row and column in that witness's image
    (N, 3; -1 where none), over which :func:`restore_consistent` compares readings."""

    segments: np.ndarray
    owners: np.ndarray
    witnesses: tuple[tuple[CameraModel, np.ndarray], ...]
    surfaces: np.ndarray
    pixels: np.ndarray


def image_coordinates(points: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distorted pixel coordinates (u, v) of world ``points`` (N, 3) in ``camera`` (NaN behind it) and their
    depth z along its axis."""
    device = rigid_transform(np.asarray(points, dtype=np.float64), np.asarray(camera.R), np.asarray(camera.t))
    z = device[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        zz = np.where(z > 0.0, z, np.nan)
        terms, tilt = opencv_distortion_terms(camera.dist)
        u, v = distorted_pixels(device[:, 0] / zz, device[:, 1] / zz, np.asarray(camera.K), terms, tilt)
    return u, v, z


def _pixel_index(points: np.ndarray, camera: CameraModel) -> np.ndarray:
    """Flat index of the pixel nearest each point's image (-1 outside the image or behind the camera)."""
    u, v, _ = image_coordinates(points, camera)
    return nearest_pixel_index(u, v, camera.width, camera.height)


def depth_map(points: np.ndarray, camera: CameraModel, pixel: np.ndarray | None = None) -> np.ndarray:
    """The camera's z-buffer of ``points`` (N, 3) world mm: (height, width) depths, +inf where no point falls
    (``pixel``: the points' flat pixel indices, when known)."""
    points = np.asarray(points, dtype=np.float64)
    if pixel is None:
        u, v, z = image_coordinates(points, camera)
        pixel = nearest_pixel_index(u, v, camera.width, camera.height)
    else:
        z = rigid_transform(points, np.asarray(camera.R), np.asarray(camera.t))[:, 2]
    buffer = np.full(camera.height * camera.width, np.inf)
    splat_nearest(buffer, pixel, z)
    return buffer.reshape(camera.height, camera.width)


def smooth_surfaces(depth: np.ndarray, camera: CameraModel, jump_mm: float = DEFAULT_JUMP_MM
                    ) -> tuple[np.ndarray, int]:
    """The smooth surfaces of a depth map: (height, width) labels 1..count of 4-connected measured pixels with no
    depth jump between them (:func:`skirt_segments`' threshold), 0 where none; and the count."""
    K = np.asarray(camera.K, dtype=np.float64)
    focal = 0.5 * (K[0, 0] + K[1, 1])
    finite = np.isfinite(depth)
    with np.errstate(invalid="ignore"):
        jump = np.maximum(jump_mm, JUMP_SLOPE * np.where(finite, depth, 0.0) / focal)
        right = np.abs(depth[:, 1:] - depth[:, :-1]) <= np.minimum(jump[:, 1:], jump[:, :-1])
        down = np.abs(depth[1:] - depth[:-1]) <= np.minimum(jump[1:], jump[:-1])
    # a pixel joins its surface's interior unless a jump or a hole lies beside it; edge pixels then take the
    # label of an interior neighbour (the surface across a jump begins with edge pixels of its own)
    interior = finite.copy()
    interior[:, 1:] &= right
    interior[:, :-1] &= right
    interior[1:] &= down
    interior[:-1] &= down
    count, labels = cv2.connectedComponents(interior.astype(np.uint8), connectivity=4)
    grown = cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.intp)
    labels = np.where(finite & (labels == 0), grown, labels)
    return labels, count - 1


def _window(depth: np.ndarray, reach_px: int, largest: bool) -> np.ndarray:
    """The smallest (or largest) finite depth within ``reach_px`` of each pixel (+inf, or -inf, where none)."""
    size = 2 * int(reach_px) + 1
    square = np.ones((size, size), np.uint8)
    if largest:
        values = np.where(np.isfinite(depth), depth, -np.inf)
        return cv2.dilate(values, square, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    return cv2.erode(depth, square, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)


def skirt_segments(depth: np.ndarray, camera: CameraModel, jump_mm: float = DEFAULT_JUMP_MM,
                   hole_reach_px: int = DEFAULT_HOLE_REACH_PX) -> np.ndarray:
    """The skirts of the space behind a camera's depth map: (M, 2, 3) world segments along the camera's rays.

    Parameters
    ----------
    depth : (height, width) array
        The camera's z-buffer of the cloud it measured (:func:`depth_map`), +inf where no point fell.
    camera : CameraModel
        The camera.
    jump_mm : float
        The smallest depth jump between neighbouring pixels taken as a discontinuity.
    hole_reach_px : int
        How far around a pixel without a point the depths are taken to bound what it hides.

    Returns
    -------
    segments : (M, 2, 3) array
        World points: each segment runs along the ray between two neighbouring pixels, from just behind the
        nearer depth to just before the farther one.

    Notes
    -----
    Space behind the depth map is unknown to the camera: the region U = {X : z(X) > Z(pixel of X)}. Its boundary
    is the measured surface plus, between neighbouring pixels p, q with Z_q - Z_p > J, the ray surface from
    depth Z_p to Z_q: a thermal ray from a measured point that passes through U crosses it there. The jump
    threshold J = max(jump_mm, 4 f^-1 Z_p) allows a surface up to atan 4 = 76 degrees steep between neighbours
    (f the focal length in pixels: Z/f is the pixel footprint). A pixel without a point sees a surface at an
    unknown depth. Beside such a hole, the depths within ``hole_reach_px`` bound what it may hide: from a
    measured pixel beside it a skirt runs back to the largest depth around (behind the measured surface, so it
    never stands in free space), and, where a nearer surface lies within the reach by more than the slope over
    the reach allows, from the smallest depth around to the measured pixel (the hole may hold that surface's
    unseen continuation: a part's flank the projector leaves dark). Skirts start and end half a threshold inside
    the jump, so that the surfaces at their ends keep their own points. This is the free-space reasoning of
    volumetric carving [1]_ applied to the one question the fusion asks: is a thermal ray free?

    References
    ----------
    .. [1] K. N. Kutulakos and S. M. Seitz, "A Theory of Shape by Space Carving", International Journal of
       Computer Vision 38(3), 199-218, 2000.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"The depth map must be {camera.height}x{camera.width} for this camera; got {depth.shape}.")
    if not jump_mm > 0 or hole_reach_px < 1:
        raise ValueError(f"The jump must be positive and the hole reach at least 1 pixel; got {jump_mm} mm and "
                         f"{hole_reach_px} px.")
    K = np.asarray(camera.K, dtype=np.float64)
    focal = 0.5 * (K[0, 0] + K[1, 1])
    finite = np.isfinite(depth)
    lowest = _window(depth, hole_reach_px, largest=False)
    highest = _window(depth, hole_reach_px, largest=True)
    starts, ends, middles = [], [], []
    for axis in (0, 1):
        first = [slice(None), slice(None)]
        second = [slice(None), slice(None)]
        first[axis], second[axis] = slice(None, -1), slice(1, None)
        a, b = depth[tuple(first)], depth[tuple(second)]
        fa, fb = finite[tuple(first)], finite[tuple(second)]
        with np.errstate(invalid="ignore"):  # the few pairs that may hold a skirt: a hole beside, or a jump
            row, column = np.nonzero((fa ^ fb) | (np.abs(a - b) > jump_mm))
        row_b, column_b = (row + 1, column) if axis == 0 else (row, column + 1)
        a, b = depth[row, column], depth[row_b, column_b]
        fa, fb = finite[row, column], finite[row_b, column_b]
        both = fa & fb
        near = np.minimum(a, b)  # the measured one beside a hole (+inf)
        # both measured: a jump; one measured, one hole: back to the farthest depth around, and forward from
        # the nearest one around where it lies before the measured pixel by more than a slope allows
        around_low = np.minimum(lowest[row, column], lowest[row_b, column_b])
        around_high = np.maximum(highest[row, column], highest[row_b, column_b])
        reach_jump = np.maximum(jump_mm, JUMP_SLOPE * near / focal * (hole_reach_px + 1))
        forward = ~both & (near - around_low > reach_jump)
        far = np.where(both, np.maximum(a, b), np.maximum(around_high, near))
        near = np.where(forward, around_low, near)
        threshold = np.maximum(jump_mm, JUMP_SLOPE * near / focal)
        emit = far - near > threshold
        half = 0.5 * threshold[emit]
        starts.append(near[emit] + half)
        ends.append(far[emit] - half)
        middles.append(np.column_stack([column[emit] + (0.5 if axis == 1 else 0.0),
                                        row[emit] + (0.5 if axis == 0 else 0.0)]))
    start, end, middle = np.concatenate(starts), np.concatenate(ends), np.concatenate(middles)
    if len(start) == 0:
        return np.empty((0, 2, 3))
    rays = np.column_stack([normalized_coordinates(middle, K, camera.dist), np.ones(len(middle))])
    R, t = np.asarray(camera.R, dtype=np.float64), np.asarray(camera.t, dtype=np.float64)
    segments = np.empty((len(start), 2, 3))
    for end_index, along in enumerate((start, end)):
        device = rays * along[:, None]
        segments[:, end_index] = (device - t) @ R  # R^T (x - t) for each row
    return segments


def coarser(camera: CameraModel, factor: int) -> CameraModel:
    """The same camera with ``factor`` times fewer pixels a side (pixel (u, v) becomes ((u + 0.5) / factor - 0.5,
    ...); distortion is in normalised units, so it stays)."""
    if factor == 1:
        return camera
    K = np.array(camera.K, dtype=np.float64)
    K[:2, :2] /= factor
    K[:2, 2] = (K[:2, 2] + 0.5) / factor - 0.5
    return camera.replace(width=-(-camera.width // factor), height=-(-camera.height // factor), K=K)


def unseen_space(points: np.ndarray, witnesses: Sequence[Witness], jump_mm: float = DEFAULT_JUMP_MM,
                 hole_reach_px: int = DEFAULT_HOLE_REACH_PX, factor: int = 1) -> UnseenSpace:
    """The skirts of the space that none of ``witnesses`` saw into, from the cloud ``points`` (N, 3) world mm.

    Each camera's skirts come from its own rows of the cloud (:func:`skirt_segments`); a skirt's samples that
    another witness (a projector, another head) sees past are carved away when they are drawn
    (:func:`occluder_samples`): space is free where any device saw through it.
    """
    points = np.asarray(points, dtype=np.float64)
    surfaces = np.full(len(points), -1, dtype=np.intp)
    pixels = np.full((len(points), 3), -1, dtype=np.intp)
    finite = np.isfinite(points).all(axis=1)
    rows_of, located = [], []
    # with coarser images, one measured point per block of the witness's own pixels draws its depth maps
    sampled = np.ones(len(points), dtype=bool)
    if factor > 1:
        for witness in witnesses:
            if witness.pixels is not None:
                column, row = np.rint(np.asarray(witness.pixels, dtype=np.float64)).T
                with np.errstate(invalid="ignore"):
                    on_grid = (np.mod(column, factor) == 0) & (np.mod(row, factor) == 0)
                sampled[slice(None) if witness.rows is None else witness.rows] &= on_grid
    witnesses = [Witness(coarser(witness.camera, factor), witness.rows, witness.skirts,
                         None if witness.pixels is None else (np.asarray(witness.pixels, dtype=np.float64) + 0.5) / factor - 0.5)
                 for witness in witnesses]
    for witness in witnesses:
        rows = np.arange(len(points)) if witness.rows is None else np.asarray(witness.rows, dtype=np.intp)
        keep = finite[rows]
        if witness.pixels is None:  # located for its depth map alone
            rows = rows[keep]
            rows = rows[sampled[rows]]
            pixel = _pixel_index(points[rows], witness.camera)
        else:
            u, v = witness.pixels[keep].T
            pixel = nearest_pixel_index(u, v, witness.camera.width, witness.camera.height)
            rows = rows[keep]
        rows_of.append(rows)
        located.append(pixel)
    maps = []
    for rows, pixel, witness in zip(rows_of, located, witnesses):
        drawn = sampled[rows]
        depth = depth_map(points[rows[drawn]], witness.camera, pixel[drawn])
        if not witness.skirts:
            # a projector finer than the camera gets the camera's points on every other pixel or so: the gaps
            # between them take the nearest depth around (less free space, never more)
            gaps = np.isinf(depth)
            depth[gaps] = _window(depth, PROJECTOR_GAP_PX, largest=False)[gaps]
        maps.append((witness.camera, depth))
    segments, owners, numbered = [], [], 0
    for index, (rows, pixel, witness) in enumerate(zip(rows_of, located, witnesses)):
        if not witness.skirts:
            continue
        camera, depth = maps[index]
        labels, count = smooth_surfaces(depth, camera, jump_mm)
        at = pixel >= 0
        found = labels.ravel()[pixel[at]]
        surfaces[rows[at]] = np.where(found > 0, found + numbered, -1)
        pixels[rows[at], 0] = index
        pixels[rows[at], 1], pixels[rows[at], 2] = np.divmod(pixel[at], camera.width)
        numbered += count
        segments.append(skirt_segments(depth, camera, jump_mm, hole_reach_px))
        owners.append(np.full(len(segments[-1]), index, dtype=np.intp))
    if not segments:
        return UnseenSpace(np.empty((0, 2, 3)), np.empty(0, dtype=np.intp), tuple(maps), surfaces, pixels)
    return UnseenSpace(np.concatenate(segments), np.concatenate(owners), tuple(maps), surfaces, pixels)


CONSISTENT_K = 20.0
"""How far (K) beyond three robust standard deviations from the median of its neighbours' readings a reading
that only the skirts would take away may lie and still be kept."""
VOUCH_RADIUS_PX = 3
"""The neighbours that vouch for a reading: within this many pixels of the witness's image, on its surface."""
MIN_VOUCHING = 8
"""Readings of neighbours needed before they vouch for (or against) a reading."""


MIN_SURFACE_READINGS = 20
"""Carved readings a smooth surface needs before its median vouches for a reading on it."""


def _surface_ranges(carved: np.ndarray, surfaces: np.ndarray, tolerance_k: float) -> tuple[np.ndarray, np.ndarray]:
    """Per surface label, median -+ (tolerance + 3 robust sigma) of its carved readings; an empty range for a
    surface with fewer than ``MIN_SURFACE_READINGS``."""
    count = int(surfaces.max()) + 1 if len(surfaces) else 0
    low, high = np.full(count, np.inf), np.full(count, -np.inf)
    vouching = np.flatnonzero(np.isfinite(carved) & (surfaces >= 0))
    order = vouching[np.argsort(surfaces[vouching], kind="stable")]
    labels, first, counts = np.unique(surfaces[order], return_index=True, return_counts=True)
    for label, start, size in zip(labels, first, counts):
        if size < MIN_SURFACE_READINGS:
            continue
        values = carved[order[start:start + size]]
        median = np.median(values)
        reach = tolerance_k + 3.0 * 1.4826 * np.median(np.abs(values - median))
        low[label], high[label] = median - reach, median + reach
    return low, high


def _row_medians(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The median of each row's finite values (``counts`` of them, at least one): NaN sorts last, so the
    middle of the sorted row's first ``counts`` (numpy's nanmedian takes a masked-array path ten times slower)."""
    ordered = np.sort(values, axis=1)
    rows = np.arange(len(values))
    return 0.5 * (ordered[rows, (counts - 1) // 2] + ordered[rows, counts // 2])


def restore_consistent(plain: np.ndarray, carved: np.ndarray, space: UnseenSpace,
                       tolerance_k: float = CONSISTENT_K) -> np.ndarray:
    """The carved temperatures, with the readings that only the skirts took away given back where their
    neighbours on the same smooth surface vouch for them.

    Parameters
    ----------
    plain, carved : (N,) arrays
        The points' temperatures (degrees C, NaN unseen) without and with the skirts as occluders.
    space : UnseenSpace
        Its ``surfaces`` and ``pixels``: where each point lies in its witness's image, and on which surface.
    tolerance_k : float
        The margin beyond three robust standard deviations of the neighbours' readings.

    Returns
    -------
    temperature : (N,) array

    Notes
    -----
    A skirt bounds the space a camera could not see into, not what fills it: behind a fixture's edge it also
    lies where the thermal camera in fact sees the part past the fixture. A thermal ray through unseen space
    that met an unseen occluder reads the occluder's temperature, which differs from the readings beside it on
    the same smooth surface (a cool wall read at the temperature of the hot flank in front of it, or a hot part
    read at a cool fixture's). A reading T only the skirts took away is therefore kept where

        |T - median| <= tolerance_k + 3 * 1.4826 * MAD

    over the readings of its neighbours within ``VOUCH_RADIUS_PX`` on its surface (MAD their median absolute
    deviation; 1.4826 MAD is a robust standard deviation [2]_), given at least ``MIN_VOUCHING`` of them, and
    also over all the carved readings of its surface. A reading kept vouches in turn, so a band of kept readings
    grows inward from the seen ones, ring by ring; a reading whose neighbours disagree is dropped, and so is one
    no neighbour reaches. The temperature of a forging varies smoothly over a surface seen without a depth
    jump, while an occluder's edge changes the reading by hundreds of kelvin within a thermal pixel, so the
    growth stops there. The whole surface's test holds where the skirts missed some occluded readings, which
    then read hot beside the ones they took and would vouch for them: their median is the wall's, unmoved by
    the few. Its neighbours' test holds where a surface's own temperatures span more than an occluder's
    reading differs from them (a hot support with a gradient).

    References
    ----------
    .. [2] P. J. Rousseeuw and C. Croux, "Alternatives to the Median Absolute Deviation", Journal of the American
       Statistical Association 88(424), 1273-1283, 1993.
    """
    plain, carved = np.asarray(plain), np.asarray(carved)
    result = carved.copy()
    placed = space.pixels[:, 0] >= 0
    pending = np.flatnonzero(np.isfinite(plain) & np.isnan(carved) & placed & (space.surfaces >= 0))
    if len(pending) == 0:
        return result
    shapes = [(camera.height, camera.width) for camera, _ in space.witnesses]
    offsets = np.concatenate([[0], np.cumsum([h * w for h, w in shapes])])
    widths = np.array([w for _, w in shapes])
    heights = np.array([h for h, _ in shapes])
    flat = np.where(placed, offsets[space.pixels[:, 0]] + space.pixels[:, 1] * widths[space.pixels[:, 0]]
                    + space.pixels[:, 2], 0)
    value = np.full(offsets[-1], np.nan)
    label = np.full(offsets[-1], -1, dtype=np.intp)
    vouching = np.flatnonzero(np.isfinite(carved) & placed)
    value[flat[vouching]] = carved[vouching]
    label[flat[placed]] = space.surfaces[placed]
    low, high = _surface_ranges(carved, space.surfaces, tolerance_k)
    reading = plain[pending]
    pending = pending[(reading >= low[space.surfaces[pending]]) & (reading <= high[space.surfaces[pending]])]
    dy, dx = np.mgrid[-VOUCH_RADIUS_PX:VOUCH_RADIUS_PX + 1, -VOUCH_RADIUS_PX:VOUCH_RADIUS_PX + 1]
    dy, dx = dy.ravel(), dx.ravel()

    def windows(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The flat pixels of each point's window, and which lie in its image."""
        witness, row, column = space.pixels[points].T
        rows, columns = row[:, None] + dy, column[:, None] + dx
        inside = (rows >= 0) & (rows < heights[witness][:, None])
        inside &= (columns >= 0) & (columns < widths[witness][:, None])
        at = offsets[witness][:, None] + np.clip(rows, 0, None) * widths[witness][:, None] + np.clip(columns, 0, None)
        return np.where(inside, at, 0), inside

    waiting = np.full(offsets[-1], -1, dtype=np.intp)  # the pending point at each pixel
    waiting[flat[pending]] = pending
    # the first frontier: pending readings with a vouching reading within the window (on any surface)
    reach = np.ones((2 * VOUCH_RADIUS_PX + 1,) * 2, np.uint8)
    near = np.concatenate([cv2.dilate(np.isfinite(value[offsets[index]:offsets[index + 1]]).reshape(shape)
                                      .astype(np.uint8), reach).ravel() for index, shape in enumerate(shapes)])
    frontier = pending[near[flat[pending]] > 0]
    while len(frontier):
        at, inside = windows(frontier)
        around = np.where(inside & (label[at] == space.surfaces[frontier][:, None]), value[at], np.nan)
        counted = np.isfinite(around).sum(axis=1)
        judged = counted >= MIN_VOUCHING
        median = _row_medians(around[judged], counted[judged])
        spread = _row_medians(np.abs(around[judged] - median[:, None]), counted[judged])
        settled = frontier[judged]
        agrees = np.abs(plain[settled] - median) <= tolerance_k + 3.0 * 1.4826 * spread
        kept = settled[agrees]
        result[kept] = plain[kept]
        value[flat[kept]] = plain[kept]
        waiting[flat[settled]] = -1  # judged: kept or dropped for good
        # the next frontier: the readings still waiting beside the ones just kept
        at, inside = windows(kept)
        beside = np.unique(waiting[at[inside]])
        frontier = beside[beside >= 0]
    return result


def occluder_samples(space: UnseenSpace, view: CameraModel, depth_tolerance_mm: float) -> np.ndarray:
    """Points (S, 3) along the skirts, dense enough for ``view`` (one per pixel of a skirt's image there), less
    those that a witness other than the skirt's own sees past by more than ``depth_tolerance_mm``."""
    samples, owner = segment_samples(space.segments, view)
    if len(space.witnesses) > 1:  # carved by the witnesses other than the skirt's own
        keep = np.ones(len(samples), dtype=bool)
        sample_owner = space.owners[owner]
        for index, (camera, depth) in enumerate(space.witnesses):
            others = np.flatnonzero(keep & (sample_owner != index))
            keep[others] = ~_seen_past(samples[others], camera, depth, depth_tolerance_mm)
        samples = samples[keep]
    return samples


def segment_samples(segments: np.ndarray, view: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """Points along (M, 2, 3) segments, one per pixel of each segment's image in ``view`` (at least its two
    ends, at most ``MAX_SAMPLES_PER_SEGMENT``; the z-buffer's 3x3 fill closes the diagonal gaps): the points
    (S, 3) and the segment each lies on (S,)."""
    if len(segments) == 0:
        return np.empty((0, 3)), np.empty(0, dtype=np.intp)
    u, v, _ = image_coordinates(segments.reshape(-1, 3), view)
    length = np.hypot(u[0::2] - u[1::2], v[0::2] - v[1::2])
    count = np.where(np.isfinite(length), np.ceil(length) + 1, 2).astype(np.intp)
    np.clip(count, 2, MAX_SAMPLES_PER_SEGMENT, out=count)
    owner = np.repeat(np.arange(len(segments)), count)
    first = np.cumsum(count) - count
    step = np.arange(len(owner)) - np.repeat(first, count)
    fraction = step / np.repeat(count - 1, count)
    return segments[owner, 0] + fraction[:, None] * (segments[owner, 1] - segments[owner, 0]), owner


def _seen_past(samples: np.ndarray, camera: CameraModel, depth: np.ndarray, tolerance_mm: float) -> np.ndarray:
    """Samples in front of the camera's measured depth by more than the tolerance: free space for that camera."""
    u, v, z = image_coordinates(samples, camera)
    pixel = nearest_pixel_index(u, v, camera.width, camera.height)
    seen = np.zeros(len(samples), dtype=bool)
    at = np.flatnonzero(pixel >= 0)
    measured = depth.ravel()[pixel[at]]
    # +inf (nothing measured there) is unknown, not seen past
    seen[at] = np.isfinite(measured) & (z[at] < measured - tolerance_mm)
    return seen
