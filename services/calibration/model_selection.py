"""Choosing the lens distortion model from the calibration data: the Bayesian information criterion."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class ModelFit:
    """One candidate lens model fitted to the views.

    Attributes
    ----------
    model : str
        The distortion model's name.
    residual_sum : float
        Sum of the squared reprojection residuals over every coordinate, in px^2.
    observations : int
        Number of residual coordinates (twice the number of features).
    parameters : int
        Number of estimated parameters: intrinsics, distortion coefficients and six per view pose.
    bic : float
        ``n ln(RSS / n) + k ln n``.
    rms : float
        Reprojection RMS per feature, in px.
    """

    model: str
    residual_sum: float
    observations: int
    parameters: int
    bic: float
    rms: float


@dataclass(frozen=True)
class ModelSelection:
    """The chosen model, every candidate's fit, and why."""

    chosen: str
    fits: tuple[ModelFit, ...]
    reason: str


def bayesian_information_criterion(residual_sum: float, observations: int, parameters: int) -> float:
    """BIC of a least-squares fit with Gaussian residuals of unknown variance.

    Parameters
    ----------
    residual_sum : float
        Sum of squared residuals, RSS.
    observations : int
        Number of residuals, n.
    parameters : int
        Number of fitted parameters, k.

    Returns
    -------
    float
        ``n ln(RSS / n) + k ln n``; lower is better.

    Notes
    -----
    ``-2 ln L`` of the maximum-likelihood Gaussian fit is ``n ln(RSS / n)`` up to a constant, and each
    parameter costs ``ln n`` [1]_: an extra coefficient is kept only when it lowers the RSS by more than a
    factor ``n^(-1/n)``, about ``ln n`` residual variances.

    References
    ----------
    .. [1] G. Schwarz, "Estimating the dimension of a model", Annals of Statistics 6(2), 461-464 (1978).
    """
    if observations <= parameters or residual_sum <= 0:
        raise ValueError(f"The BIC needs more observations ({observations}) than parameters ({parameters}) and a "
                         f"positive residual sum (got {residual_sum}).")
    return observations * math.log(residual_sum / observations) + parameters * math.log(observations)


def select_model(fits: list[ModelFit]) -> ModelSelection:
    """The candidate of lowest BIC, with a one-sentence reason naming the runner-up.

    Parameters
    ----------
    fits : list of ModelFit
        The candidates, simplest first (a tie goes to the simpler).

    Returns
    -------
    ModelSelection
    """
    if not fits:
        raise ValueError("Model selection needs at least one fitted candidate.")
    best = min(range(len(fits)), key=lambda i: (fits[i].bic, i))
    chosen = fits[best]
    others = [fit for fit in fits if fit is not chosen]
    if not others:
        return ModelSelection(chosen=chosen.model, fits=tuple(fits), reason=f"{chosen.model} was the only candidate")
    runner_up = min(others, key=lambda fit: fit.bic)
    change = 100 * (1 - runner_up.residual_sum / chosen.residual_sum)
    extra = runner_up.parameters - chosen.parameters
    if extra > 0:
        reason = (f"{chosen.model} has the lowest BIC ({chosen.bic:.1f}); {runner_up.model}'s {extra} more "
                  f"parameters lower the residual sum by only {change:.2f} % (BIC {runner_up.bic:.1f}), "
                  "less than the data can tell from noise")
    else:
        reason = (f"{chosen.model} has the lowest BIC ({chosen.bic:.1f}); {runner_up.model} with {-extra} fewer "
                  f"parameters leaves a residual sum {-change:.2f} % larger (BIC {runner_up.bic:.1f}): the data "
                  "support the extra coefficients")
    return ModelSelection(chosen=chosen.model, fits=tuple(fits), reason=reason)
