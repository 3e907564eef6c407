"""The tetrahedral mesh class (numpy): arrays, per-vertex attributes and cached
geometry.

:class:`TetMesh` holds the arrays of a mesh and exposes the free functions of
:mod:`mi_tetvr.mesh.topology` over them as cached properties (trimesh's
style): each is computed on first access and kept until ``vertices`` or
``tets`` is assigned anew.
"""
from __future__ import annotations

import numpy as np

from mi_tetvr.mesh.topology import (Topology, build_topology, edge_lengths, geometry_summary,
                                    quality, signed_volumes, validate_arrays,
                                    validate_attributes)

__all__ = ["TetMesh", "DEFAULT_COLOR", "DEFAULT_OPACITY"]

#: Defaults for meshes that lack an attribute: white emission, unit extinction.
DEFAULT_COLOR = (1.0, 1.0, 1.0)
DEFAULT_OPACITY = 1.0


def _cached(func):
    """A read-only property computed once and kept in ``self._cache`` (cleared
    when ``vertices`` or ``tets`` is assigned). Array results are made
    read-only so that the cached value cannot be changed by accident."""
    name = func.__name__

    def get(self):
        cache = self._cache
        if name not in cache:
            value = func(self)
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
            cache[name] = value
        return cache[name]

    get.__name__ = name
    get.__doc__ = func.__doc__
    return property(get)


class TetMesh:
    """A tetrahedral mesh with per-vertex color and opacity (numpy).

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    color : (n, 3) float, optional
        Linear RGB emission per unit extinction; default :data:`DEFAULT_COLOR`.
    opacity : (n,) float, optional
        Extinction per unit length (>= 0); default :data:`DEFAULT_OPACITY`.
    point_data : dict of str -> (n, ...) array, optional
        Other per-vertex arrays (kept for writing and for selection).
    cell_data : dict of str -> (m, ...) array, optional
        Per-tet arrays (listed and written; meshes derived by refinement drop
        them; :func:`~mi_tetvr.mesh.io.read_tetmesh` converts them to point
        data on request).
    topology : Topology, optional
        :func:`~mi_tetvr.mesh.build_topology` of these arrays when it was built
        already (a fit hands it on to its ``tetmesh``): kept, not rebuilt.
    duplicates : bool, optional
        Look for duplicate tets now (default). False where :attr:`topology` is
        built next anyway (the ``tetmesh`` shape): its face matching finds and
        names them, and the tets are not sorted twice.

    Attributes
    ----------
    vertices : (n, 3) float64
    tets : (m, 4) int64
        As given (not re-oriented; :attr:`topology` holds the oriented tets).
    color : (n, 3) float64
    opacity : (n,) float64
    point_data : dict of str -> (n, ...) array
    cell_data : dict of str -> (m, ...) array

    Notes
    -----
    The arrays are validated (:func:`~mi_tetvr.mesh.validate_arrays`) and
    copied on construction. A mesh is immutable by convention: change it by
    making a new one (:meth:`transformed`, :func:`~mi_tetvr.mesh.refine_mesh`,
    ...), never by writing into its arrays in place. Assigning
    :attr:`vertices` or :attr:`tets` anew validates the new array and drops
    the cached properties. :attr:`topology` is built lazily, once, by
    :func:`~mi_tetvr.mesh.build_topology`.
    """

    def __init__(self, vertices, tets, color=None, opacity=None, point_data=None,
                 cell_data=None, topology=None, duplicates=True):
        self._cache = {}
        self._vertices, self._tets = validate_arrays(vertices, tets, duplicates=duplicates)
        if topology is not None:
            # the topology of these very arrays, built before (handed on, not rebuilt)
            if topology.tets.shape != self._tets.shape or not np.array_equal(
                    np.sort(topology.tets, axis=1), np.sort(self._tets, axis=1)):
                raise ValueError("TetMesh: the topology given is not that of these tets")
            self._cache["topology"] = topology
        n = len(self._vertices)
        color, opacity = validate_attributes(n, color, opacity)
        self.color = np.tile(np.asarray(DEFAULT_COLOR, float), (n, 1)) if color is None else color
        self.opacity = np.full(n, DEFAULT_OPACITY) if opacity is None else opacity
        self.point_data = dict(point_data or {})
        self.cell_data = dict(cell_data or {})
        for name, arrays, count in (("point", self.point_data, n),
                                    ("cell", self.cell_data, len(self._tets))):
            bad = {k: len(a) for k, a in arrays.items() if len(a) != count}
            if bad:
                raise ValueError(f"{name} data arrays {bad} do not have {count} entries "
                                 f"(one per {'vertex' if name == 'point' else 'tet'})")

    # -- arrays ------------------------------------------------------------------
    @property
    def vertices(self) -> np.ndarray:
        """(n, 3) float64 vertex positions."""
        return self._vertices

    @vertices.setter
    def vertices(self, value):
        n = len(self._vertices)
        if np.ndim(value) != 2 or len(value) != n:
            raise ValueError(f"vertices must keep their shape ({n}, 3) (color and opacity "
                             f"are per vertex), got {np.shape(value)}")
        self._vertices, _ = validate_arrays(value, self._tets)
        self._cache.clear()

    @property
    def tets(self) -> np.ndarray:
        """(m, 4) int64 vertex indices of each tet, as given."""
        return self._tets

    @tets.setter
    def tets(self, value):
        _, self._tets = validate_arrays(self._vertices, value)
        self._cache.clear()

    # -- cached geometry -----------------------------------------------------------
    @_cached
    def topology(self) -> Topology:
        """:class:`~mi_tetvr.mesh.Topology` (:func:`~mi_tetvr.mesh.build_topology`)."""
        return build_topology(self._vertices, self._tets, check=False)  # validated at init

    @_cached
    def volumes(self) -> np.ndarray:
        """(m,) float64 signed volumes of :attr:`tets` as given
        (:func:`~mi_tetvr.mesh.signed_volumes`)."""
        return signed_volumes(self._vertices, self._tets)

    @_cached
    def quality(self) -> np.ndarray:
        """(m,) float64 quality of :attr:`tets` as given
        (:func:`~mi_tetvr.mesh.quality`; negative for inverted tets)."""
        return quality(self._vertices, self._tets)

    @_cached
    def edge_lengths(self) -> np.ndarray:
        """(m, 6) float64 edge lengths of each tet, in the order of
        :data:`~mi_tetvr.mesh.EDGES` (:func:`~mi_tetvr.mesh.edge_lengths`)."""
        return edge_lengths(self._vertices, self._tets)

    @_cached
    def mean_edge_length(self) -> float:
        """Mean of :attr:`edge_lengths`, the mesh's cell size
        (:func:`~mi_tetvr.mesh.mean_edge_length`)."""
        return float(self.edge_lengths.mean())

    @_cached
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: min and max corner."""
        return np.stack([self._vertices.min(0), self._vertices.max(0)])

    # -- derived meshes and reports ------------------------------------------------
    def transformed(self, matrix):
        """A copy with vertices mapped by a 4x4 affine matrix."""
        m = np.asarray(matrix, dtype=np.float64)
        v = self._vertices @ m[:3, :3].T + m[:3, 3]
        return TetMesh(v, self._tets, self.color, self.opacity, self.point_data, self.cell_data)

    def summary(self) -> dict:
        """:func:`~mi_tetvr.mesh.geometry_summary` plus the ranges of color and
        opacity and the data arrays: ``arrays`` maps each name to its kind
        (``point`` or ``cell``), shape and value range."""
        def entry(kind, a):
            a = np.asarray(a, np.float64)
            return {"kind": kind, "shape": list(a.shape),
                    "range": [float(np.nanmin(a)), float(np.nanmax(a))] if a.size else None}
        return {**geometry_summary(self._vertices, self.topology),
                "color_range": [float(self.color.min()), float(self.color.max())],
                "opacity_range": [float(self.opacity.min()), float(self.opacity.max())],
                "arrays": {**{k: entry("point", a) for k, a in self.point_data.items()},
                           **{k: entry("cell", a) for k, a in self.cell_data.items()}}}
