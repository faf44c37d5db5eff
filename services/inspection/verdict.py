"""Conformity decisions with measurement uncertainty: OK, NotOK, or NotDecidable."""

from __future__ import annotations

from typing import Literal

Verdict = Literal["OK", "NotOK", "NotDecidable"]


def decide(deviation: float, tolerance: tuple[float, float], expanded_uncertainty: float) -> Verdict:
    """Whether a measured deviation conforms to a tolerance, given its expanded uncertainty.

    Parameters
    ----------
    deviation : float
        Measured minus nominal.
    tolerance : (lower, upper)
        Allowed deviations, lower <= upper.
    expanded_uncertainty : float
        U (k = 2) of the measured value, >= 0.

    Returns
    -------
    verdict : {"OK", "NotOK", "NotDecidable"}

    Notes
    -----
    ISO 14253-1's rule: conformance is proven when the whole interval deviation +- U lies within
    the tolerance, non-conformance when it lies wholly outside; when a limit lies within the
    interval neither is proven and the result is ``NotDecidable`` (the ResultEvaluation of OPC
    40001-101 [1]_). A non-finite deviation or uncertainty is ``NotDecidable``.

    References
    ----------
    .. [1] OPC 40001-101 (OPC UA for Machinery, Result Transfer), ResultEvaluationEnum:
       Undefined, OK, NotOK, NotDecidable.
    """
    lower, upper = tolerance
    if lower > upper:
        raise ValueError(f"The tolerance's lower limit {lower} lies above its upper limit {upper}.")
    if not expanded_uncertainty >= 0:
        return "NotDecidable"
    if deviation - expanded_uncertainty > upper or deviation + expanded_uncertainty < lower:
        return "NotOK"
    if lower <= deviation - expanded_uncertainty and deviation + expanded_uncertainty <= upper:
        return "OK"
    return "NotDecidable"


def overall(verdicts: list[Verdict]) -> Verdict:
    """The part's verdict: NotOK if any is, else NotDecidable if any is, else OK (OK with nothing checked)."""
    if "NotOK" in verdicts:
        return "NotOK"
    if "NotDecidable" in verdicts:
        return "NotDecidable"
    return "OK"
