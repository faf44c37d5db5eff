"""Built-in thermal elongation tables against the formulas of their sources."""

import numpy as np
import pytest

from services.inspection.materials import BUILTIN_MATERIALS, Material, builtin_material

pytestmark = pytest.mark.integration


def test_carbon_steel_follows_en_1993_1_2():
    steel = builtin_material("carbon-steel")
    assert steel.strain(20.0) == pytest.approx(0.0, abs=1e-12)
    assert steel.strain(500.0) == pytest.approx(1.2e-5 * 500 + 0.4e-8 * 500**2 - 2.416e-4, abs=1e-7)
    assert steel.strain([760.0, 800.0, 860.0]) == pytest.approx([1.1e-2] * 3)  # the phase change plateau
    assert steel.strain(1000.0) == pytest.approx(2e-5 * 1000 - 6.2e-3)
    assert 90 * (1 + steel.strain(1000.0)) == pytest.approx(91.242)  # the 91.24 mm billet
    assert steel.slope(1000.0) == pytest.approx(2e-5)


def test_stainless_aluminium_titanium():
    theta = 700.0
    assert builtin_material("stainless-steel").strain(theta) == pytest.approx(
        (16 + 4.79e-3 * theta - 1.243e-6 * theta**2) * (theta - 20) * 1e-6, abs=1e-7)
    def aluminium(theta):  # EN 1999-1-2's formula is 4e-6 at 20 degC; tables are taken from 20 degC
        return 0.1e-7 * theta**2 + 22.5e-6 * theta - 4.5e-4

    assert builtin_material("aluminium").strain(400.0) == pytest.approx(aluminium(400.0) - aluminium(20.0))
    assert builtin_material("titanium-6al-4v").strain(650.0) == pytest.approx(9.7e-6 * 630)
    for material in BUILTIN_MATERIALS.values():
        assert np.all(np.diff(material.strains) >= -1e-5), material.name  # EN 1993-1-2 steps 8e-6 down at 750 degC
        assert material.source


def test_mean_strain_over_an_interval_is_the_tables_exact_integral():
    steel = builtin_material("carbon-steel")
    # across the phase change's kinks, beyond both ends of the table (clamped), and down to no width
    ends = np.array([1000.0, 700.0, 900.0, 1300.0, -30.0, 1000.0 + 1e-6])
    mean = steel.mean_strain(1000.0, ends)
    for end, value in zip(ends[1:-1], mean[1:-1]):
        t = np.linspace(1000.0, end, 400001)
        assert value == pytest.approx(np.trapezoid(steel.strain(t), t) / (end - 1000.0), abs=1e-10)
    assert mean[[0, -1]] == pytest.approx([steel.strain(1000.0)] * 2, abs=1e-10)


def test_unknown_and_invalid_tables():
    with pytest.raises(ValueError, match="unknown material 'brass'.*carbon-steel"):
        builtin_material("brass")
    with pytest.raises(ValueError, match="increase strictly"):
        Material("x", np.array([20.0, 10.0]), np.array([0.0, 1e-4]), 0.01, "")
    with pytest.raises(ValueError, match="non-finite"):
        Material("x", np.array([20.0, np.nan]), np.array([0.0, 1e-4]), 0.01, "")
