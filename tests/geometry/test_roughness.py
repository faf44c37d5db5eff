import numpy as np
import pytest

from services.geometry.roughness import local_roughness


def test_the_residual_of_a_noisy_plane_is_its_noise():
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:120, 0:160].astype(float)
    points = np.stack([u, v, 400.0 + 0.3 * u - 0.2 * v + rng.normal(0, 0.05, u.shape)], -1)
    points[40:50, 60:70] = np.nan  # a hole
    residual = local_roughness(points, 7)
    assert np.isnan(residual[45, 65])
    rms = np.sqrt(np.nanmean(residual**2))
    assert rms == pytest.approx(0.05 * np.sqrt(1 - 3 / 49), rel=0.05)  # a 3-parameter fit over 49 points


def test_an_exact_plane_has_no_roughness():
    v, u = np.mgrid[0:30, 0:30].astype(float)
    residual = local_roughness(np.stack([u, v, 2000.0 + 1.5 * u + 0.7 * v], -1), 5)
    assert np.nanmax(np.abs(residual)) < 1e-6


def test_bad_windows_and_maps_are_refused():
    with pytest.raises(ValueError, match="window"):
        local_roughness(np.zeros((10, 10, 3)), 4)
    with pytest.raises(ValueError, match="point map"):
        local_roughness(np.zeros((10, 10)), 5)
