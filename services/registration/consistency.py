"""Precision of a registration method on real pairs without ground truth: consistency under a known move.

Real infrared/visible pairs are aligned by hand only to about a pixel, so
their registration cannot be checked against a true matrix at the sub-pixel
level. What can be checked is that the method commutes with a known move:
the infrared image is moved by a similarity S and cut to a view inside it
(:func:`services.registration.synthetic_pairs.moved_view`); the registration
H1 of the view must equal the registration H0 of the whole image composed
with the move, H0 S^-1.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.registration.models import corner_error
from services.registration.synthetic_pairs import moved_view


@dataclass(frozen=True)
class MoveConsistency:
    """Consistency and distance to the hand alignment (visible pixels) of one pair, with what produced them.

    ``unmoved`` is the whole image's registration H0, ``view`` the moved view's H1, ``moved`` the moved
    infrared view and ``view_to_infrared`` S^-1 (view pixels to infrared pixels).
    """

    consistency: float
    from_hand: float
    unmoved: np.ndarray
    view: np.ndarray
    moved: np.ndarray
    view_to_infrared: np.ndarray


def move_consistency(
    register: Callable[[np.ndarray, np.ndarray], np.ndarray],
    visible: np.ndarray,
    infrared: np.ndarray,
    rng: np.random.Generator,
) -> MoveConsistency:
    """Register a pair whole and with its infrared image moved; measure how well the two agree.

    Parameters
    ----------
    register : callable
        ``register(visible, infrared) -> (3, 3) matrix`` mapping infrared to visible pixels.
    visible, infrared : 2-D arrays
        The pair, aligned by hand (the identity maps one onto the other, approximately).
    rng : numpy.random.Generator
        Draws the move: each shift component in +-30 px, rotation in +-4 degrees, scale in 0.93..1.07.

    Returns
    -------
    MoveConsistency
        ``consistency`` = mean distance of the view's four corner pixels under
        H1 and H0 S^-1 (:func:`services.registration.models.corner_error`);
        ``from_hand`` = the same distance between H0 and the identity over the
        whole infrared image.
    """
    moved, view_to_infrared = moved_view(rng, infrared)
    unmoved = register(visible, infrared)
    view = register(visible, moved)
    height, width = infrared.shape
    return MoveConsistency(
        consistency=corner_error(unmoved @ view_to_infrared, view, moved.shape[1], moved.shape[0]),
        from_hand=corner_error(np.eye(3), unmoved, width, height),
        unmoved=unmoved,
        view=view,
        moved=moved,
        view_to_infrared=view_to_infrared,
    )
