"""The uncertainty budget: from the inputs' standard uncertainties to a measure's expanded uncertainty (k = 2)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.fusion.radiometry import PlanckConstants, blackbody_counts, counts_to_temperature
from services.inspection.materials import Material

COVERAGE_FACTOR = 2.0


@dataclass(frozen=True)
class TemperatureBudget:
    """Standard uncertainties of a measured temperature (k = 1)."""

    emissivity: float = 0.85
    emissivity_uncertainty: float = 0.02
    calibration_fraction: float = 0.01
    calibration_min_k: float = 1.0
    netd_k: float = 0.05
    reflected_temperature_c: float = 20.0


def temperature_uncertainty(temperature_c: float, budget: TemperatureBudget,
                            constants: PlanckConstants | None = None) -> dict[str, float]:
    """Standard uncertainty of a temperature, kelvin, by source, and their root sum of squares.

    Parameters
    ----------
    temperature_c : float
        The measured temperature, degrees C.
    budget : TemperatureBudget
        Emissivity (assumed value and its uncertainty), calibration and NETD.
    constants : PlanckConstants, optional
        The camera's Planck curve (default the typical long-wave curve of the fusion).

    Returns
    -------
    dict
        ``emissivity``, ``calibration``, ``netd`` and ``total`` in kelvin.

    Notes
    -----
    A grey body of true emissivity e + u_e read with the assumed e gives the signal
    S = (e + u_e) P(T) + (1 - e - u_e) P(T_refl); the emissivity term is the difference between
    the temperature the radiometric correction returns for S and T (the sensitivity of the
    camera's Planck curve, not a linearised law). Calibration: max(min_k, fraction * T).
    """
    constants = constants or PlanckConstants()
    true_emissivity = min(budget.emissivity + budget.emissivity_uncertainty, 1.0)
    signal = (true_emissivity * blackbody_counts(temperature_c, constants)
              + (1 - true_emissivity) * blackbody_counts(budget.reflected_temperature_c, constants))
    emissivity = abs(float(counts_to_temperature(signal, constants, budget.emissivity,
                                                 budget.reflected_temperature_c)) - temperature_c)
    calibration = max(budget.calibration_min_k, budget.calibration_fraction * abs(temperature_c))
    total = float(np.sqrt(emissivity**2 + calibration**2 + budget.netd_k**2))
    return {"emissivity": emissivity, "calibration": calibration, "netd": budget.netd_k, "total": total}


def size_uncertainty(cold_value: float, mean_temperature_c: float, temperature_std_k: float, material: Material,
                     material_fraction: float, fit_std_mm: float, systematic_mm: float) -> dict[str, float]:
    """Standard uncertainties (mm, k = 1) of a size measure (diameter, distance) by source, and U (k = 2).

    Parameters
    ----------
    cold_value : float
        The cold-equivalent size L, mm.
    mean_temperature_c : float
        Mean temperature of the feature's points.
    temperature_std_k : float
        Standard uncertainty of that temperature (``temperature_uncertainty``'s total, plus any
        fallback share), kelvin.
    material : Material
        Its elongation table.
    material_fraction : float
        The table's relative standard uncertainty.
    fit_std_mm : float
        The fit's own (random, structured-light noise) standard deviation of L.
    systematic_mm : float
        Structured-light error common to the feature's points, already scaled to L.

    Returns
    -------
    dict
        ``fit``, ``structured_light``, ``temperature``, ``material``, ``combined`` and ``expanded``.

    Notes
    -----
    L_cold = L_hot / (1 + eps(T)), so dL_cold/dT = -L_cold eps'(T) / (1 + eps(T)) and
    dL_cold/d eps = -L_cold / (1 + eps). Temperature and table errors are taken as common to all
    points of the feature (fully correlated, the conservative case), the fit's as random; the
    terms are combined in quadrature (GUM, JCGM 100:2008, 5.1.2) and U = 2 u_c.
    """
    strain = float(material.strain(mean_temperature_c))
    slope = float(material.slope(mean_temperature_c))
    terms = {
        "fit": fit_std_mm,
        "structured_light": systematic_mm,
        "temperature": abs(cold_value) * slope / (1 + strain) * temperature_std_k,
        "material": abs(cold_value) * material_fraction * abs(strain) / (1 + strain),
    }
    combined = float(np.sqrt(sum(value**2 for value in terms.values())))
    return {**terms, "combined": combined, "expanded": COVERAGE_FACTOR * combined}
