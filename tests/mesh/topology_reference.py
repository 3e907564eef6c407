"""The tet topology as the project built it before its linear-time rewrite
(numpy ``np.unique`` over face rows): kept verbatim as the reference that
:func:`mi_tetvr.mesh.build_topology` must reproduce exactly."""
import warnings

import numpy as np

from mi_tetvr.mesh.topology import (EDGES, FACES, FLAT_TOLERANCE, REPAIR_HINT, MeshError,
                                    Orientation, Topology)

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


def flip_tets(tets, mask):
    """Reverse the orientation of some tets by swapping local vertices 2 and 3.

    Parameters
    ----------
    tets : (m, 4) int
    mask : (m,) bool
        Tets to flip.

    Returns
    -------
    (m, 4) int
        A copy (same dtype) with the masked tets flipped; their local
        vertices 0 and 1 keep their slot.
    """
    out = np.array(tets, copy=True)
    mask = np.asarray(mask, dtype=bool)
    out[mask] = out[mask][:, [0, 1, 3, 2]]
    return out


def orient_tets(vertices, tets, flat_tol=FLAT_TOLERANCE) -> Orientation:
    """Orient tets positively by flipping the inverted ones.

    A tet counts as flat when ``|volume| <= flat_tol * l**3``, ``l`` its
    longest edge (or when its volume is NaN); flat tets keep their vertex
    order (the sign of their volume is rounding noise), every other tet with
    a negative volume is flipped (:func:`flip_tets`). ``flat_tol = 0`` flips
    every tet with a negative volume and counts only exact zeros as flat.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    flat_tol : float
        Flatness tolerance relative to each tet's size, default :data:`FLAT_TOLERANCE`.

    Returns
    -------
    Orientation
        ``(tets, volumes, flipped, flat)``; ``tets`` is a copy.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets)
    vol = signed_volumes(vertices, tets)
    longest = edge_lengths(vertices, tets).max(axis=1) if len(tets) else np.zeros(0)
    flat = ~(np.abs(vol) > flat_tol * longest ** 3)  # NaN volumes count as flat
    flipped = (vol < 0) & ~flat
    return Orientation(flip_tets(tets, flipped), vol, flipped, flat)


def edge_lengths(vertices, tets):
    """Lengths of the six edges of each tet, in the order of :data:`EDGES`.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int

    Returns
    -------
    (m, 6) float64
        An edge shared by several tets appears once per tet.
    """
    return np.linalg.norm(_edge_vectors(vertices, tets), axis=-1)


def _edge_vectors(vertices, tets):
    """(m, 6, 3) float64: ``p_i - p_j`` for each local edge ``(i, j)`` of :data:`EDGES`."""
    v, t = np.asarray(vertices, dtype=np.float64), np.asarray(tets)
    return v[t[:, EDGES[:, 0]]] - v[t[:, EDGES[:, 1]]]


def validate_arrays(vertices, tets, *, strict=True, allow_empty=False):
    """Check the arrays of a tet mesh; returns float64 vertices and int64 tets.

    Parameters
    ----------
    vertices : (n, 3) float or None
        ``None`` checks ``tets`` alone (then without the index range).
    tets : (m, 4) int
    strict : bool
        True: every check below, and the arrays returned are copies. False:
        the cheap checks only (shapes, at least one tet, index range), and
        no copies where the dtypes already match; for algorithms that take
        a mesh as it comes (refinement, the regularizer).
    allow_empty : bool
        Accept a mesh without tets.

    Returns
    -------
    vertices : (n, 3) float64 or None
    tets : (m, 4) int64

    Raises
    ------
    MeshError
        Wrong shapes, no tets; indices out of range; with ``strict`` also
        non-integer indices, non-finite positions, a repeated vertex in a tet
        or duplicate tets. The message names the offending indices.
    """
    if vertices is not None:
        vertices = np.asarray(vertices) if strict else np.asarray(vertices, dtype=np.float64)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise MeshError(f"vertices must have shape (n, 3), got {vertices.shape}")
    tets = np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(
            f"tets must have shape (m, 4) (linear tetrahedra), got {tets.shape}")
    if len(tets) == 0 and not allow_empty:
        raise MeshError("the mesh has no tetrahedra")
    if strict and not np.issubdtype(tets.dtype, np.integer):
        if not np.all(np.isfinite(tets)) or np.any(tets != np.round(tets)):
            raise MeshError("tet indices must be integers")
    tets = tets.astype(np.int64, copy=strict)
    if vertices is None:
        return None, tets
    if strict:
        vertices = vertices.astype(np.float64)
        bad = np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))
        if len(bad):
            raise MeshError(f"non-finite (NaN/inf) vertex positions at vertices {_preview(bad)}")
    n = len(vertices)
    if len(tets) and (tets.min() < 0 or tets.max() >= n):
        bad = np.flatnonzero(np.any((tets < 0) | (tets >= n), axis=1))
        raise MeshError(f"tet vertex indices out of range [0, {n}) in tets {_preview(bad)}")
    if strict:
        s = np.sort(tets, axis=1)
        bad = np.flatnonzero(np.any(s[:, 1:] == s[:, :-1], axis=1))
        if len(bad):
            raise MeshError(f"tets with a repeated vertex index: {_preview(bad)}; {REPAIR_HINT}")
        _, counts = np.unique(s, axis=0, return_counts=True)
        if np.any(counts > 1):
            dup_keys = np.flatnonzero(counts > 1)
            inv = np.unique(s, axis=0, return_inverse=True)[1].ravel()
            bad = np.flatnonzero(np.isin(inv, dup_keys))
            raise MeshError(f"duplicate tets (same four vertices): {_preview(bad)}; "
                            f"{REPAIR_HINT}")
    return vertices, tets


def face_keys(faces):
    """A key per triangle that does not depend on the order of its vertices.

    Parameters
    ----------
    faces : (k, 3) int
        Triangles, e.g. the faces of tets, ``tets[:, FACES].reshape(-1, 3)``.

    Returns
    -------
    (k,) int64
        Equal exactly for triangles with the same three vertices, and
        ordered as the sorted vertex triples are (lexicographically): the
        sorted triple packed into 63 bits when every index is below 2**21,
        else the rank of the sorted triple among the distinct ones.
    """
    s = np.sort(np.asarray(faces, dtype=np.int64).reshape(-1, 3), axis=1)
    if len(s) == 0:
        return np.zeros(0, np.int64)
    if s.max() < 2 ** 21:  # pack the triple into one int64: much faster unique
        return (s[:, 0] << 42) | (s[:, 1] << 21) | s[:, 2]
    return np.unique(s, axis=0, return_inverse=True)[1].ravel().astype(np.int64)


def _face_parity(tri):
    """Orientation class of each oriented triangle (k, 3): True when the cyclic
    rotation starting at its smallest index is increasing."""
    r = np.argmin(tri, axis=1)
    idx = (r[:, None] + np.arange(3)) % 3
    rot = np.take_along_axis(tri, idx, axis=1)
    return rot[:, 1] < rot[:, 2]


def _face_pairs(faces):
    """Group equal triangles (any vertex order): ``(inv, counts, fa, fb)``
    with ``inv`` each face's group, ``counts`` each group's size and
    ``fa, fb`` the two faces of each group of two."""
    _, inv, counts = np.unique(face_keys(faces), return_inverse=True, return_counts=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    sorted_inv = inv[order]
    start = np.flatnonzero(np.r_[True, sorted_inv[1:] != sorted_inv[:-1]])
    paired = start[counts[sorted_inv[start]] == 2]
    return inv, counts, order[paired], order[paired + 1]


def _match_faces(tets):
    """Pair up the faces of oriented tets.

    Returns (faces (m*4, 3), neighbors (m*4,), neighbor_faces (m*4,), fa, fb)
    where fa, fb are the flat face indices of each interior face pair."""
    m = len(tets)
    faces = tets[:, FACES].reshape(-1, 3)
    inv, counts, fa, fb = _face_pairs(faces)
    if np.any(counts > 2):
        bad_keys = np.flatnonzero(counts > 2)
        bad = np.flatnonzero(np.isin(inv, bad_keys)) // 4
        raise MeshError(
            f"{len(bad_keys)} face(s) shared by more than two tets (non-manifold mesh); "
            f"tets involved: {_preview(np.unique(bad))}; {REPAIR_HINT}")
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
    tets, vol, flip, flat = orient_tets(vertices, tets)
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
            tets = flip_tets(tets, to_flip)
            faces, neighbors, neighbor_faces, fa, fb = _match_faces(tets)

    par = _face_parity(faces)
    n_inconsistent = int(np.count_nonzero(par[fa] == par[fb]))
    if n_inconsistent:
        raise MeshError(
            f"{n_inconsistent} interior face(s) are not shared with opposite orientation "
            f"even after orienting every tet: the mesh folds over itself "
            f"(tets {_preview(np.unique(fa[par[fa] == par[fb]] // 4))}); {REPAIR_HINT}")
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
