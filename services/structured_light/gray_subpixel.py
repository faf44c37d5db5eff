"""Sub-pixel projector coordinates from Gray code alone: stripe boundaries located in the camera image.

A Gray-code-only capture decodes each camera pixel to a stripe, ``2**d`` projector pixels wide (``d`` the
finest bit shown), and the stripe centre is a staircase of depth. Between two neighbouring stripes exactly
one Gray bit flips, so in the camera image the boundary is where that bit's plane crosses its inverse (or
the white/black mid level). Located there to a fraction of a camera pixel, the boundaries are the known
projector coordinates ``2**d k - 1/2`` at sub-pixel camera positions, and the coordinate of every pixel is
interpolated between the two boundaries that bracket it.
"""

from __future__ import annotations

import numba
import numpy as np

from services.formats.sequence import AXES, Axis, Sequence

_MAX_STRIPES_BETWEEN_PIXELS = 2  # more boundaries between two neighbours: a bit flips twice, not locatable
_STRIPE_TOLERANCE = 1.5  # a result within a misread finest bit of the pixel's own stripe centre
_MAX_BOUNDARY_GAP_STRIPES = 4  # brackets may span three lost boundaries of a washed-out fine plane
_FIT_BOUNDARIES_PER_SIDE = 2  # a line through two boundaries each side: wider windows feel the curvature


@numba.njit(cache=True, inline="always")
def _plane_signal(frames, plane_frame, plane_complement, plane_sign, reference, bit, row, col):
    """Signed distance of the plane showing ``bit`` from its threshold at one pixel: > 0 where the bit is 1."""
    value = float(frames[plane_frame[bit], row, col])
    other = reference[row, col] if plane_complement[bit] < 0 else float(frames[plane_complement[bit], row, col])
    return plane_sign[bit] * (value - other)


@numba.njit(cache=True, inline="always")
def _trailing_zeros(value):
    count = 0
    while value & 1 == 0:
        value >>= 1
        count += 1
    return count


# Hand-written with numba: a scan along each row that pairs neighbours, locates the crossings and
# interpolates between them; numpy would need ragged per-row lists of boundaries.
@numba.njit(parallel=True, cache=True)
def _subpixel_kernel(frames, plane_frame, plane_complement, plane_sign, reference, stripe, stripe_width, reach, out):
    height, width = stripe.shape
    for row in numba.prange(height):
        capacity = _MAX_STRIPES_BETWEEN_PIXELS * width + 1
        position = np.empty(capacity)  # camera column of each boundary, in scan order
        coordinate = np.empty(capacity)  # its projector coordinate
        segment = np.empty(capacity, np.int64)  # the run of decoded pixels it lies in
        weight = np.empty(capacity)  # inverse variance of its position, up to a common factor: (D(u) - D(u+1))^2
        pixel_segment = np.empty(width, np.int64)
        run = 0
        for col in range(width):
            if stripe[row, col] < 0:
                run += 1
            pixel_segment[col] = run
        n = 0
        for col in range(width - 1):
            first, second = stripe[row, col], stripe[row, col + 1]
            if first < 0 or second < 0 or first == second:
                continue
            low, steps = min(first, second), abs(second - first)
            if steps > _MAX_STRIPES_BETWEEN_PIXELS:
                continue  # a misread bit, or stripes too narrow for the camera: no boundary here
            start = n
            for j in range(1, steps + 1):
                upper = low + j  # the boundary between stripes upper - 1 and upper
                bit = _trailing_zeros(upper)
                if bit >= plane_frame.size:
                    continue
                a = _plane_signal(frames, plane_frame, plane_complement, plane_sign, reference, bit, row, col)
                b = _plane_signal(frames, plane_frame, plane_complement, plane_sign, reference, bit, row, col + 1)
                if not a * b < 0.0:
                    continue  # the plane does not cross its threshold between the two pixels: misread
                position[n] = col + a / (a - b)
                weight[n] = (a - b) * (a - b)
                coordinate[n] = stripe_width * upper - 0.5
                segment[n] = pixel_segment[col]
                n += 1
            if n - start == 2:
                if second < first:  # the coordinate falls along the scan: its boundaries in scan order
                    position[start], position[start + 1] = position[start + 1], position[start]
                    weight[start], weight[start + 1] = weight[start + 1], weight[start]
                    coordinate[start], coordinate[start + 1] = coordinate[start + 1], coordinate[start]
                if position[start + 1] < position[start]:  # crossings out of order by noise: both at their mean
                    position[start] = position[start + 1] = 0.5 * (position[start] + position[start + 1])
        # A boundary crossed back and forth by noise appears several times in a row: keep the mean crossing.
        m = 0
        i = 0
        while i < n:
            j, total, least = i + 1, position[i], weight[i]
            while j < n and coordinate[j] == coordinate[i] and segment[j] == segment[i]:
                total += position[j]
                least = min(least, weight[j])
                j += 1
            position[m], coordinate[m], segment[m], weight[m] = total / (j - i), coordinate[i], segment[i], least
            m += 1
            i = j
        n = m
        right = 0  # first boundary right of the pixel
        for col in range(width):
            out[row, col] = np.nan
            k = stripe[row, col]
            if k < 0:
                continue
            while right < n and position[right] <= col:
                right += 1
            here = pixel_segment[col]
            left_ok = right >= 1 and segment[right - 1] == here
            right_ok = right < n and segment[right] == here
            if left_ok and right_ok:
                a, b = right - 1, right
            elif left_ok and right >= 2 and segment[right - 2] == here:
                a, b = right - 2, right - 1  # past the last boundary of the run: extrapolate its last interval
            elif right_ok and right + 1 < n and segment[right + 1] == here:
                a, b = right, right + 1
            else:
                continue
            span = coordinate[b] - coordinate[a]
            distance = position[b] - position[a]
            if span == 0.0 or abs(span) > _MAX_BOUNDARY_GAP_STRIPES * stripe_width or not distance > 0.0:
                continue
            if not (left_ok and right_ok):
                nearest = position[b] if col > position[b] else position[a]
                if abs(col - nearest) > distance:
                    continue  # too far beyond the boundaries to extrapolate
            value = coordinate[a] + span * (col - position[a]) / distance
            if reach > 1:
                # A line through up to ``reach`` boundaries on each side, weighted by the inverse variance
                # of their positions: washed-out fine planes (narrow stripes, grazing light) count little.
                first, last = a, b
                for _ in range(reach - 1):  # widen the window while the boundaries run on in step
                    if first > 0 and segment[first - 1] == here and position[first - 1] < position[first] and \
                            0 < (coordinate[first] - coordinate[first - 1]) * span <= span * span * 2:
                        first -= 1
                    if last + 1 < n and segment[last + 1] == here and position[last + 1] > position[last] and \
                            0 < (coordinate[last + 1] - coordinate[last]) * span <= span * span * 2:
                        last += 1
                count = last - first + 1
                if count > 2:
                    sw = su = sc = suu = suc = 0.0
                    for i in range(first, last + 1):
                        du, w = position[i] - col, weight[i]
                        sw += w
                        su += w * du
                        sc += w * coordinate[i]
                        suu += w * du * du
                        suc += w * du * coordinate[i]
                    determinant = sw * suu - su * su
                    if determinant > 0:
                        value = (suu * sc - su * suc) / determinant
            if abs(value - (stripe_width * k + 0.5 * (stripe_width - 1))) <= _STRIPE_TOLERANCE * stripe_width:
                out[row, col] = value


def _threshold_image(frames: np.ndarray, sequence: Sequence) -> np.ndarray:
    """What planes without an inverse are compared with, as in ``decode``: the white/black mid level, else the
    offset of the last phase group."""
    white, black = sequence.white_index, sequence.black_index
    if white is not None and black is not None:
        return 0.5 * (frames[white].astype(np.float64) + frames[black])
    groups = [group for axis in AXES for group in sequence.phase_groups(axis)]
    if groups:
        return frames[list(groups[-1].frames)].mean(axis=0)
    return np.zeros(frames.shape[1:])  # every plane has its inverse


def gray_subpixel(frames: np.ndarray, sequence: Sequence, axis: Axis, stripe_centres: np.ndarray) -> np.ndarray:
    """Sub-pixel projector coordinates of a Gray-code-only axis from its stripe boundaries.

    Parameters
    ----------
    frames : (F, H, W) uint8 or uint16 array
        The capture, in the manifest's order.
    sequence : Sequence
        Its manifest; ``axis`` must be coded by Gray code alone.
    axis : {"x", "y"}
        The projector axis.
    stripe_centres : (H, W) array
        The decoded stripe-centre coordinates of the axis (``decode``'s), NaN where not decoded.

    Returns
    -------
    coordinates : (H, W) float32 array
        Projector coordinates (pixel centres at integers), NaN where a pixel is not decoded or has no
        boundaries to interpolate between.

    Notes
    -----
    With stripes ``s = 2**d`` wide, the boundary between stripes ``k - 1`` and ``k`` is at projector
    coordinate ``c_k = s k - 1/2`` and only Gray bit ``d + tz(k)`` flips there (``tz`` the number of trailing
    zero bits). Where two neighbouring camera pixels ``u`` and ``u + 1`` of a scan line are decoded to
    stripes ``k - 1`` and ``k``, that bit's plane signal ``D = I - I_inverse`` (or ``I - (I_white +
    I_black) / 2``) changes sign and the boundary lies at ``u_k = u + D(u) / (D(u) - D(u + 1))``, the zero
    crossing of the blurred edge. A pixel ``u`` between boundaries ``u_a <= u < u_b`` of one run of decoded
    pixels gets ``c = c_a + (c_b - c_a) (u - u_a) / (u_b - u_a)`` [1]_, refined to the weighted least-squares
    line ``c(u)`` through up to two boundaries on each side (those that run on in step), each weighted by
    ``(D(u) - D(u + 1))^2``, the inverse variance of its position up to the common noise: boundaries of a
    plane washed out by blur or grazing light count little. Past a run's last boundary its last interval is
    extrapolated by up to its own length. Scan lines are the camera rows, or the columns when
    they cross more stripe boundaries (stripes along the rows): for a rig whose baseline runs along the
    coded axis, the image axis nearer the epipolar direction. Boundaries that disagree with the decoded
    stripes (no sign change, more than two stripes between neighbours) are not used; a bracket may span up
    to four stripes (the boundaries of a fine plane that blur or grazing light washes out are lost, those of
    the coarser planes around them still bracket the pixel). The result is refused (NaN) where it lies more
    than 1.5 stripes from the pixel's own stripe centre: further than a misread finest bit can put it.

    References
    ----------
    .. [1] M. Trobina, "Error model of a coded-light range sensor", Technical report BIWI-TR-164, ETH Zurich
       (1995): stripe edges where a Gray plane and its inverse cross, to sub-pixel precision; J. Salvi,
       J. Pages, J. Batlle, "Pattern codification strategies in structured light systems", Pattern
       Recognition 37(4), 827-849 (2004).
    """
    frames = np.asarray(frames)
    stripe_centres = np.asarray(stripe_centres)
    if frames.ndim != 3 or stripe_centres.shape != frames.shape[1:]:
        raise ValueError(f"The frames must be a (F, H, W) stack and the stripe centres an (H, W) image; got "
                         f"shapes {frames.shape} and {stripe_centres.shape}.")
    planes = sequence.gray_planes(axis)
    if not planes or sequence.phase_groups(axis):
        raise ValueError(f"Projector axis {axis} is not coded by Gray code alone, so it has no stripe boundaries "
                         "to interpolate between.")
    finest = planes[0].bit
    width = float(1 << finest)
    plane_frame = np.array([p.frame for p in planes], np.int64)  # index: bit - finest
    plane_complement = np.array([-1 if p.complement is None else p.complement for p in planes], np.int64)
    plane_sign = np.array([-1.0 if p.inverted else 1.0 for p in planes])
    with np.errstate(invalid="ignore"):
        stripe = np.where(np.isfinite(stripe_centres), np.rint((stripe_centres - 0.5 * (width - 1)) / width), -1)
    stripe = stripe.astype(np.int64)
    reference = _threshold_image(frames, sequence)
    decoded = stripe >= 0
    changes_along_rows = np.count_nonzero((stripe[:, 1:] != stripe[:, :-1]) & decoded[:, 1:] & decoded[:, :-1])
    changes_along_columns = np.count_nonzero((stripe[1:] != stripe[:-1]) & decoded[1:] & decoded[:-1])
    along_columns = changes_along_columns > changes_along_rows
    if along_columns:
        frames, reference, stripe = frames.transpose(0, 2, 1), reference.T, stripe.T
    out = np.empty(stripe.shape, np.float32)
    _subpixel_kernel(np.ascontiguousarray(frames), plane_frame, plane_complement, plane_sign,
                     np.ascontiguousarray(reference), np.ascontiguousarray(stripe), width, _FIT_BOUNDARIES_PER_SIDE,
                     out)
    return np.ascontiguousarray(out.T) if along_columns else out
