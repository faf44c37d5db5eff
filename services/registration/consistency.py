"""Precision of a registration method on real pairs without ground truth: consistency under a known move.

Real infrared/visible pairs are aligned by hand only to about a pixel, so
their registration cannot be checked against a true matrix at the sub-pixel
level. What can be checked is that the method commutes with a known move:
the infrared image is moved by a similarity S
(:func:`services.registration.synthetic_pairs.moved_image`, what the move
brings in from outside masked; or, stricter, cut to a view inside the
original, :func:`services.registration.synthetic_pairs.moved_view`); the
registration H1 of the moved image must equal the registration H0 of the
whole image composed with the move, H0 S^-1.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.registration.models import corner_error
from services.registration.synthetic_pairs import moved_image, moved_view


@dataclass(frozen=True)
class MoveConsistency:
    """Consistency and distance to the hand alignment (visible pixels) of one pair, with what produced them.

    ``unmoved`` is the whole image's registration H0, ``moved`` the moved image's H1, ``moved_image`` the moved
    infrared image with ``moved_mask`` its pixels that have data (None for a view: all), and
    ``moved_to_infrared`` S^-1 (moved pixels to infrared pixels).
    """

    consistency: float
    from_hand: float
    unmoved: np.ndarray
    moved: np.ndarray
    moved_image: np.ndarray
    moved_mask: np.ndarray | None
    moved_to_infrared: np.ndarray


def move_consistency(
    register: Callable[[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray],
    visible: np.ndarray,
    infrared: np.ndarray,
    rng: np.random.Generator,
    *,
    view: bool = False,
) -> MoveConsistency:
    """Register a pair whole and with its infrared image moved; measure how well the two agree.

    Parameters
    ----------
    register : callable
        ``register(visible, infrared, mask) -> (3, 3) matrix`` mapping infrared to visible pixels; ``mask``
        marks the infrared pixels that have data, or is None when all have.
    visible, infrared : 2-D arrays
        The pair, aligned by hand (the identity maps one onto the other, approximately).
    rng : numpy.random.Generator
        Draws the move: each shift component in +-30 px, rotation in +-4 degrees, scale in 0.93..1.07.
    view : bool
        Cut the moved image to the largest view inside the original (at most 90 % of its size) instead of
        keeping its whole canvas with what the move brought in masked: the same move, 19 % or more of
        the scene less to register, which tests how the result depends on the part of the scene seen.

    Returns
    -------
    MoveConsistency
        ``consistency`` = mean distance of the moved image's four corner
        pixels under H1 and H0 S^-1 (:func:`services.registration.models.corner_error`);
        ``from_hand`` = the same distance between H0 and the identity over the
        whole infrared image.
    """
    if view:
        (moved_infrared, moved_to_infrared), mask = moved_view(rng, infrared), None
    else:
        moved_infrared, mask, moved_to_infrared = moved_image(rng, infrared)
    unmoved = register(visible, infrared, None)
    moved = register(visible, moved_infrared, mask)
    height, width = infrared.shape
    return MoveConsistency(
        consistency=corner_error(unmoved @ moved_to_infrared, moved, moved_infrared.shape[1],
                                 moved_infrared.shape[0]),
        from_hand=corner_error(np.eye(3), unmoved, width, height),
        unmoved=unmoved,
        moved=moved,
        moved_image=moved_infrared,
        moved_mask=mask,
        moved_to_infrared=moved_to_infrared,
    )
