"""Tetrahedral mesh topology and validation (numpy).

This module is the only place where topology is made. Everything downstream
(the ``tetmesh`` shape, the ``tetvr`` integrator, file I/O) takes its
``Topology`` from :func:`build_topology`.

Conventions
-----------
* A tet ``(v0, v1, v2, v3)`` is *positively oriented* when
  ``det(p1 - p0, p2 - p0, p3 - p0) > 0``.
* Local face ``i`` is the face opposite local vertex ``i``. Its vertices, in
  the order of :data:`FACES`, wind counter-clockwise seen from outside a
  positively oriented tet (the right-hand normal points outward).
* ``neighbors[t, i]`` is the tet across face ``i`` of tet ``t`` (``-1`` on the
  boundary) and ``neighbor_faces[t, i]`` the local index of that face in the
  neighbour.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np

#: Local vertex indices of face i (opposite vertex i), outward-oriented.
FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)

#: Relative tolerance (of the bounding-box diagonal cubed) below which a tet
#: counts as flat (zero volume).
FLAT_TOLERANCE = 1e-12


class MeshError(ValueError):
    """Raised for invalid tetrahedral mesh input; the message names the problem
    and the offending indices."""


def _preview(idx, limit=10):
    idx = np.asarray(idx).ravel()
    s = ", ".join(str(int(i)) for i in idx[:limit])
    return s + (f", ... ({len(idx)} in all)" if len(idx) > limit else "")


def signed_volumes(vertices, tets):
    """Signed volumes of tets.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int

    Returns
    -------
    (m,) float64, positive for positively oriented tets.
    """
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(tets)]
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def validate_arrays(vertices, tets):
    """Check shapes, finiteness and index ranges; returns float64 vertices and
    int64 tets. Raises :class:`MeshError` with the offending indices."""
    vertices = np.asarray(vertices)
    tets = np.asarray(tets)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"vertices must have shape (n, 3), got {vertices.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(
            f"tets must have shape (m, 4) (linear tetrahedra), got {tets.shape}")
    if len(tets) == 0:
        raise MeshError("the mesh has no tetrahedra")
    if not np.issubdtype(tets.dtype, np.integer):
        if not np.all(np.isfinite(tets)) or np.any(tets != np.round(tets)):
            raise MeshError("tet indices must be integers")
    tets = tets.astype(np.int64)
    vertices = vertices.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))
    if len(bad):
        raise MeshError(f"non-finite (NaN/inf) vertex positions at vertices {_preview(bad)}")
    bad = np.flatnonzero(np.any((tets < 0) | (tets >= len(vertices)), axis=1))
    if len(bad):
        raise MeshError(
            f"tet vertex indices out of range [0, {len(vertices)}) in tets {_preview(bad)}")
    s = np.sort(tets, axis=1)
    bad = np.flatnonzero(np.any(s[:, 1:] == s[:, :-1], axis=1))
    if len(bad):
        raise MeshError(f"tets with a repeated vertex index: {_preview(bad)}")
    _, first, counts = np.unique(s, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup_keys = np.flatnonzero(counts > 1)
        inv = np.unique(s, axis=0, return_inverse=True)[1].ravel()
        bad = np.flatnonzero(np.isin(inv, dup_keys))
        raise MeshError(f"duplicate tets (same four vertices): {_preview(bad)}")
    return vertices, tets


def validate_attributes(n_vertices, color=None, opacity=None):
    """Check per-vertex color (n, 3) and opacity (n,); returns float64 copies
    (``None`` stays ``None``)."""
    out = []
    for name, arr, shape in (("color", color, (n_vertices, 3)),
                             ("opacity", opacity, (n_vertices,))):
        if arr is None:
            out.append(None)
            continue
        arr = np.asarray(arr, dtype=np.float64)
        if name == "opacity" and arr.ndim == 2 and arr.shape[1] == 1:
            arr = arr[:, 0]
        if arr.shape != shape:
            raise MeshError(f"{name} must have shape {shape}, got {arr.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(arr.reshape(n_vertices, -1)), axis=1))
        if len(bad):
            raise MeshError(f"non-finite {name} at vertices {_preview(bad)}")
        if name == "opacity":
            bad = np.flatnonzero(arr < 0)
            if len(bad):
                raise MeshError(
                    f"negative opacity (extinction must be >= 0) at vertices {_preview(bad)}")
        out.append(arr)
    return tuple(out)


def _face_parity(tri):
    """Orientation class of each oriented triangle (k, 3): True when the cyclic
    rotation starting at its smallest index is increasing."""
    r = np.argmin(tri, axis=1)
    idx = (r[:, None] + np.arange(3)) % 3
    rot = np.take_along_axis(tri, idx, axis=1)
    return rot[:, 1] < rot[:, 2]


@dataclasses.dataclass(frozen=True)
class Topology:
    """Topology of a tetrahedral mesh.

    Attributes
    ----------
    tets : (m, 4) int32
        Positively oriented tets (flat tets oriented consistently with their
        neighbours).
    neighbors : (m, 4) int32
        Tet across local face i, -1 on the boundary.
    neighbor_faces : (m, 4) int8
        Local index of that face in the neighbour, -1 on the boundary.
    boundary_faces : (b, 3) int32
        Boundary triangles, wound counter-clockwise seen from outside.
    boundary_tets : (b,) int32
        Tet behind each boundary face.
    boundary_local_faces : (b,) int8
        Local face index of each boundary face in its tet.
    boundary_adjacency : (b, 3) int32
        Boundary face across the edge opposite each corner of each boundary
        face (any one where the surface is non-manifold), -1 if none.
    volumes : (m,) float64
        Volumes (>= 0) of the oriented tets.
    flat : (m,) bool
        Zero-volume tets (kept: the renderer steps over them safely).
    n_flipped : int
        Number of tets whose orientation was fixed.
    """
    tets: np.ndarray
    neighbors: np.ndarray
    neighbor_faces: np.ndarray
    boundary_faces: np.ndarray
    boundary_tets: np.ndarray
    boundary_local_faces: np.ndarray
    boundary_adjacency: np.ndarray
    volumes: np.ndarray
    flat: np.ndarray
    n_flipped: int

    @property
    def n_tets(self):
        return len(self.tets)


def _match_faces(tets):
    """Pair up the faces of oriented tets.

    Returns (faces (m*4, 3), neighbors (m*4,), neighbor_faces (m*4,), fa, fb)
    where fa, fb are the flat face indices of each interior face pair."""
    m = len(tets)
    faces = tets[:, FACES].reshape(-1, 3)
    keys = np.sort(faces, axis=1)
    if keys.max() < 2 ** 21:  # pack the triple into one int64: much faster unique
        keys = (keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2]
        _, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    else:
        _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    if np.any(counts > 2):
        bad_keys = np.flatnonzero(counts > 2)
        bad = np.flatnonzero(np.isin(inv, bad_keys)) // 4
        raise MeshError(
            f"{len(bad_keys)} face(s) shared by more than two tets (non-manifold mesh); "
            f"tets involved: {_preview(np.unique(bad))}")
    order = np.argsort(inv, kind="stable")
    sorted_inv = inv[order]
    start = np.flatnonzero(np.r_[True, sorted_inv[1:] != sorted_inv[:-1]])
    paired = start[counts[sorted_inv[start]] == 2]
    fa, fb = order[paired], order[paired + 1]
    neighbors = np.full(m * 4, -1, dtype=np.int64)
    neighbor_faces = np.full(m * 4, -1, dtype=np.int64)
    neighbors[fa], neighbors[fb] = fb // 4, fa // 4
    neighbor_faces[fa], neighbor_faces[fb] = fb % 4, fa % 4
    return faces, neighbors, neighbor_faces, fa, fb


def _edge_adjacency(tris):
    """(b, 3): triangle across the edge opposite each corner, -1 if none."""
    b = len(tris)
    adj = np.full((b, 3), -1, dtype=np.int64)
    if b == 0:
        return adj.astype(np.int32)
    e = np.stack([tris[:, [1, 2]], tris[:, [2, 0]], tris[:, [0, 1]]], 1).reshape(-1, 2)
    e = np.sort(e, axis=1)
    key = e[:, 0] * (int(tris.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    k = key[order]
    same = np.flatnonzero(k[1:] == k[:-1])
    a, c = order[same], order[same + 1]
    adj.ravel()[a] = c // 3
    adj.ravel()[c] = a // 3
    return adj.astype(np.int32)


def build_topology(vertices, tets, *, warn=True) -> Topology:
    """Orient tets, match faces, find the boundary.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    warn : bool
        Emit warnings for repaired input (inverted or flat tets).

    Returns
    -------
    Topology

    Raises
    ------
    MeshError
        Bad indices, non-finite positions, duplicate tets or faces shared by
        more than two tets.
    """
    vertices, tets = validate_arrays(vertices, tets)
    m = len(tets)
    vol = signed_volumes(vertices, tets)
    diag = float(np.linalg.norm(np.ptp(vertices, axis=0))) or 1.0
    flat = np.abs(vol) <= FLAT_TOLERANCE * diag ** 3
    flip = (vol < 0) & ~flat
    tets = tets.copy()
    tets[flip] = tets[flip][:, [0, 1, 3, 2]]
    faces, neighbors, neighbor_faces, fa, fb = _match_faces(tets)

    # Flat tets have no geometric orientation: orient them so that the faces
    # they share with oriented neighbours appear with opposite winding.
    oriented = ~flat
    while True:
        par = _face_parity(faces)
        ta, tb = fa // 4, fb // 4
        bad = par[fa] == par[fb]
        to_flip = np.zeros(m, bool)
        to_flip[ta[bad & ~oriented[ta] & oriented[tb]]] = True
        to_flip[tb[bad & ~oriented[tb] & oriented[ta]]] = True
        newly = np.zeros(m, bool)
        newly[ta[~bad & ~oriented[ta] & oriented[tb]]] = True
        newly[tb[~bad & ~oriented[tb] & oriented[ta]]] = True
        if not (to_flip.any() or newly.any()):
            break
        oriented |= to_flip | newly
        if to_flip.any():
            tets[to_flip] = tets[to_flip][:, [0, 1, 3, 2]]
            faces, neighbors, neighbor_faces, fa, fb = _match_faces(tets)

    par = _face_parity(faces)
    n_inconsistent = int(np.count_nonzero(par[fa] == par[fb]))
    if n_inconsistent:
        raise MeshError(
            f"{n_inconsistent} interior face(s) are not shared with opposite orientation "
            f"even after orienting every tet: the mesh folds over itself "
            f"(tets {_preview(np.unique(fa[par[fa] == par[fb]] // 4))})")
    n_flipped = int(np.count_nonzero(flip))
    n_flat = int(np.count_nonzero(flat))
    if warn and n_flipped:
        warnings.warn(f"{n_flipped} inverted tet(s) re-oriented", stacklevel=2)
    if warn and n_flat:
        warnings.warn(
            f"{n_flat} zero-volume tet(s) kept (they contribute nothing; rays step "
            f"over them): {_preview(np.flatnonzero(flat))}", stacklevel=2)
    bnd = np.flatnonzero(neighbors < 0)
    bfaces = faces[bnd]
    return Topology(
        tets=tets.astype(np.int32),
        neighbors=neighbors.reshape(m, 4).astype(np.int32),
        neighbor_faces=neighbor_faces.reshape(m, 4).astype(np.int8),
        boundary_faces=bfaces.astype(np.int32),
        boundary_adjacency=_edge_adjacency(bfaces),
        boundary_tets=(bnd // 4).astype(np.int32),
        boundary_local_faces=(bnd % 4).astype(np.int8),
        volumes=np.abs(vol),
        flat=flat,
        n_flipped=n_flipped,
    )


def quality(vertices, tets):
    """Parthasarathy's smooth quality measure ``6 sqrt(2) V / l_rms^3`` per tet
    (1 for the regular tet, 0 for flat ones, negative when inverted).

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int

    Returns
    -------
    (m,) float64
    """
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(tets)]
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    l2 = sum(np.sum((p[:, i] - p[:, j]) ** 2, axis=1) for i, j in edges) / 6.0
    v = signed_volumes(vertices, tets)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 6.0 * np.sqrt(2.0) * v / np.maximum(l2, 1e-300) ** 1.5
    return q


#: Defaults for meshes that lack an attribute: white emission, unit extinction.
DEFAULT_COLOR = (1.0, 1.0, 1.0)
DEFAULT_OPACITY = 1.0


def geometry_summary(vertices, topology: Topology) -> dict:
    """Counts, bounding box, boundary, repairs and quality statistics of a mesh
    (``topology`` from :func:`build_topology` of ``vertices``)."""
    v = np.asarray(vertices, dtype=np.float64)
    q = quality(v, topology.tets)
    used = np.zeros(len(v), bool)
    used[topology.tets.ravel()] = True
    return {
        "vertices": int(len(v)),
        "unused_vertices": int(np.count_nonzero(~used)),
        "tets": int(topology.n_tets),
        "boundary_faces": int(len(topology.boundary_faces)),
        "inverted_tets_fixed": int(topology.n_flipped),
        "zero_volume_tets": int(np.count_nonzero(topology.flat)),
        "bounds_min": v.min(0).tolist(),
        "bounds_max": v.max(0).tolist(),
        "volume": float(topology.volumes.sum()),
        "quality_min": float(q.min()),
        "quality_mean": float(q.mean()),
        "quality_p01": float(np.percentile(q, 1)),
        "quality_p05": float(np.percentile(q, 5)),
        "quality_p50": float(np.percentile(q, 50)),
    }


def format_summary(d: dict) -> str:
    """Aligned ``key  value`` lines of a summary dict (floats to 6 digits)."""
    def fmt(x):
        if isinstance(x, float):
            return f"{x:.6g}"
        if isinstance(x, (list, tuple)):
            return "[" + ", ".join(fmt(y) for y in x) + "]"
        return str(x)

    width = max((len(k) for k in d), default=0)
    return "\n".join(f"{k:<{width}}  {fmt(v)}" for k, v in d.items())


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

    Topology is built lazily, once, by :func:`build_topology`.
    """

    def __init__(self, vertices, tets, color=None, opacity=None, point_data=None):
        self.vertices, self.tets = validate_arrays(vertices, tets)
        n = len(self.vertices)
        color, opacity = validate_attributes(n, color, opacity)
        self.color = np.tile(np.asarray(DEFAULT_COLOR, float), (n, 1)) if color is None else color
        self.opacity = np.full(n, DEFAULT_OPACITY) if opacity is None else opacity
        self.point_data = dict(point_data or {})
        self._topology = None

    @property
    def topology(self) -> Topology:
        if self._topology is None:
            self._topology = build_topology(self.vertices, self.tets)
        return self._topology

    @property
    def bounds(self):
        """(2, 3) float64: min and max corner."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    def transformed(self, matrix):
        """A copy with vertices mapped by a 4x4 affine matrix."""
        m = np.asarray(matrix, dtype=np.float64)
        v = self.vertices @ m[:3, :3].T + m[:3, 3]
        return TetMesh(v, self.tets, self.color, self.opacity, self.point_data)

    def summary(self) -> dict:
        """:func:`geometry_summary` plus the ranges of color and opacity and
        the point-data arrays."""
        return {**geometry_summary(self.vertices, self.topology),
                "color_range": [float(self.color.min()), float(self.color.max())],
                "opacity_range": [float(self.opacity.min()), float(self.opacity.max())],
                "point_data": {k: list(np.shape(v)) for k, v in self.point_data.items()}}
