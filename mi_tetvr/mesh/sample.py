"""A tet mesh's piecewise-linear field at arbitrary points (VTK's probe filter)."""
from __future__ import annotations

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["sample_field"]


def sample_field(vertices, tets, values, points, outside=0.0):
    """The linear interpolant of per-vertex ``values`` at ``points``.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    values : (n,) or (n, c) float
    points : (k, 3) float
    outside : float
        The value at points in no tet.

    Returns
    -------
    (k,) or (k, c) float64
    """
    with needs("vis", "sampling a mesh at points (VTK's probe filter)"):
        import pyvista as pv
    v = np.asarray(values, np.float64)
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: np.asarray(tets, np.int64)},
                               np.asarray(vertices, np.float64))
    grid.point_data["f"] = v
    probe = pv.PolyData(np.asarray(points, np.float64).reshape(-1, 3)).sample(grid)
    out = np.asarray(probe.point_data["f"], np.float64)
    found = np.asarray(probe.point_data["vtkValidPointMask"]).astype(bool)
    out[~found] = outside
    return out
