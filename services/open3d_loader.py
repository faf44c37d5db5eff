"""Open3D, imported on first use (it takes a second) and kept from clashing with numba's thread pool."""

from __future__ import annotations

from functools import cache


@cache
def open3d():
    """The ``open3d`` module, quiet except for errors.

    Open3D bundles a TBB older than numba accepts; numba is told to prefer OpenMP so that it does
    not try that TBB and warn.
    """
    import numba

    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d
