"""Tetrahedral mesh primitives, validation and topology (numpy).

This module is the only place where topology is made. Everything downstream
(the ``tetmesh`` shape, the ``tetvr`` integrator, file I/O) takes its
``Topology`` from :func:`build_topology`. It is also the one home of the
per-tet primitives the rest of the project shares: the local face and edge
tables (:data:`FACES`, :data:`EDGES`), signed volumes, orientation
(:func:`orient_tets`, :func:`flip_tets`), face keys (:func:`face_keys`), edge
lengths and quality, and input validation (:func:`validate_arrays`). All are
free functions over arrays; :class:`~mi_tetvr.mesh.TetMesh` exposes them as
cached properties.

Conventions
-----------
* A tet ``(v0, v1, v2, v3)`` is *positively oriented* when
  ``det(p1 - p0, p2 - p0, p3 - p0) > 0``.
* Local face ``i`` is the face opposite local vertex ``i``. Its vertices, in
  the order of :data:`FACES`, wind counter-clockwise seen from outside a
  positively oriented tet (the right-hand normal points outward).
* The six local edges are :data:`EDGES`, in the order ``01, 02, 03, 12, 13,
  23``; every per-edge array of shape ``(m, 6)`` follows it.
* Swapping local vertices 2 and 3 reverses a tet's orientation
  (:func:`flip_tets`); the other vertex slots keep their vertex.
* ``neighbors[t, i]`` is the tet across face ``i`` of tet ``t`` (``-1`` on the
  boundary) and ``neighbor_faces[t, i]`` the local index of that face in the
  neighbour.
"""
from __future__ import annotations

import dataclasses
import itertools
import typing
import warnings

import numpy as np

__all__ = ["FACES", "EDGES", "FLAT_TOLERANCE", "SLIVER_QUALITY", "REPAIR_HINT", "MeshError",
           "Topology", "Orientation",
           "check_bounds", "signed_volumes", "bbox_diagonal", "flip_tets", "orient_tets",
           "face_keys", "edge_lengths", "mean_edge_length", "quality", "validate_arrays",
           "validate_attributes", "build_topology", "repair_tets", "geometry_summary",
           "format_summary", "convex_boundary"]

#: Local vertex indices of face i (opposite vertex i), outward-oriented.
FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)

#: Local vertex indices of the six edges of a tet: 01, 02, 03, 12, 13, 23.
EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)

#: A tet counts as flat (zero volume) when its volume is at most this times
#: its longest edge cubed: relative to its own size, so that the tiny tets of
#: a graded mesh are not, while rounding noise (about 1e-16 times the
#: coordinates' magnitude over the edge length) stays below it for tets up to
#: 1e6 times smaller than their distance from the origin. (The regular tet
#: has 0.118; a sliver of quality 1e-3 about 1e-4.)
FLAT_TOLERANCE = 1e-9


#: Tets per chunk of the per-tet geometry (volumes, edge lengths) over big
#: meshes: bounds its float64 temporaries to about 100 MB.
CHUNK = 1 << 18


def chunk_slices(m, size=CHUNK):
    """Slices covering ``range(m)`` in pieces of ``size``."""
    return [slice(k, min(k + size, m)) for k in range(0, m, size)]


#: Tets of lower quality (:func:`quality`) that are not flat count as slivers
#: in :func:`geometry_summary`: nearly flat, they render but make positions
#: hard to optimize.
SLIVER_QUALITY = 0.01

#: How a refused mesh gets loaded: said by every refusal that repair fixes.
REPAIR_HINT = ("drop them with repair (the tetmesh property repair=true, --repair on the "
               "command line, or mi_tetvr.mesh.repair_tets)")


class MeshError(ValueError):
    """Raised for invalid tetrahedral mesh input; the message names the problem
    and the offending indices."""


def _preview(idx, limit=10):
    idx = np.asarray(idx).ravel()
    s = ", ".join(str(int(i)) for i in idx[:limit])
    return s + (f", ... ({len(idx)} in all)" if len(idx) > limit else "")


def check_bounds(bounds) -> np.ndarray:
    """An axis-aligned box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` as a
    (2, 3) float64 array; ``ValueError`` unless finite with max > min on every axis."""
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3):
        raise ValueError(f"bounds must have shape (2, 3) (min and max corner), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("bounds must be finite")
    if np.any(b[1] <= b[0]):
        raise ValueError(f"bounds must have max > min on every axis, got {b.tolist()}")
    return b


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
    return _tet_geometry(vertices, tets)[0]


def _tet_geometry(vertices, tets, edges=None):
    """``(signed volumes, edges or None)`` (m,) float64, ``edges`` per tet: its longest
    edge (``"longest"``), the mean of its six edges' lengths (``"mean"``) or of their
    squares (``"mean_square"``); in chunks of :data:`CHUNK` tets from one gather of
    their corners (no (m, 4, 3) or (m, 6, 3) arrays)."""
    vertices, tets = np.asarray(vertices, dtype=np.float64), np.asarray(tets)
    vol = np.empty(len(tets))
    edge = None if edges is None else np.empty(len(tets))
    for s in chunk_slices(len(tets)):
        p0, p1, p2, p3 = (vertices[tets[s, k]] for k in range(4))
        a, b, c = p1 - p0, p2 - p0, p3 - p0
        vol[s] = (a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1])
                  + a[:, 1] * (b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2])
                  + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])) / 6.0
        if edges is None:
            continue
        acc = np.zeros(s.stop - s.start)
        for d in (a, b, c, p2 - p1, p3 - p1, p3 - p2):       # the order of EDGES
            l2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
            if edges == "longest":
                np.maximum(acc, l2, out=acc)
            else:
                acc += np.sqrt(l2) if edges == "mean" else l2
        edge[s] = np.sqrt(acc) if edges == "longest" else acc / 6.0
    return vol, edge


def bbox_diagonal(vertices) -> float:
    """Length of the bounding-box diagonal of points (1 where it is zero or
    there are no points).

    Parameters
    ----------
    vertices : (n, 3) float

    Returns
    -------
    float
    """
    v = np.asarray(vertices, dtype=np.float64)
    if len(v) == 0:
        return 1.0
    return float(np.linalg.norm(np.ptp(v, axis=0))) or 1.0


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


class Orientation(typing.NamedTuple):
    """Result of :func:`orient_tets`.

    Attributes
    ----------
    tets : (m, 4) int
        The tets with every inverted, non-flat one flipped.
    volumes : (m,) float64
        Signed volumes of the *input* tets.
    flipped : (m,) bool
        Tets that were flipped (``volumes < 0`` and not flat).
    flat : (m,) bool
        Tets with ``|volume| <= flat_tol * diagonal**3`` (left as given).
    """
    tets: np.ndarray
    volumes: np.ndarray
    flipped: np.ndarray
    flat: np.ndarray


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
    vol, longest = _tet_geometry(vertices, tets, "longest")
    flat = ~(np.abs(vol) > flat_tol * longest ** 3)  # NaN volumes count as flat
    flipped = (vol < 0) & ~flat
    return Orientation(flip_tets(tets, flipped), vol, flipped, flat)


def _sorted3(x, y, z):
    """Elementwise ``(min, middle, max)`` of three index arrays (any integer
    type: no sums that could overflow)."""
    lo, hi = np.minimum(x, y), np.maximum(x, y)
    return np.minimum(lo, z), np.maximum(lo, np.minimum(hi, z)), np.maximum(hi, z)


#: Bits of an exact face key (:func:`face_keys`, :func:`_tet_face_keys`).
KEY_BITS = 63


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
        sorted triple ``a < b < c`` packed as ``a``, ``b - a``, ``c - a``
        into 63 bits when they fit (:func:`_pack_triples`), else the rank of
        the sorted triple among the distinct ones.
    """
    f = np.asarray(faces).reshape(-1, 3)
    if len(f) == 0:
        return np.zeros(0, np.int64)
    a, b, c = (x.astype(np.int64) for x in _sorted3(f[:, 0], f[:, 1], f[:, 2]))
    widths = _key_widths(int(c.max()) + 1, int((c - a).max()))
    if widths is not None:
        return _pack_triples(a, b, c, *widths)
    return np.unique(np.stack([a, b, c], 1), axis=0, return_inverse=True)[1].ravel().astype(
        np.int64)


def _key_widths(n_vertices, span):
    """``(bits of a, bits of a span)`` of exact face keys for vertex numbers
    below ``n_vertices`` and ``c - a`` up to ``span``; None if they do not fit
    in :data:`KEY_BITS`."""
    wa, ws = max(int(n_vertices - 1).bit_length(), 1), max(int(span).bit_length(), 1)
    return (wa, ws) if wa + 2 * ws <= KEY_BITS else None


def _pack_triples(a, b, c, wa, ws):
    """Sorted triples (int64 arrays ``a < b < c``) packed exactly, ordered as
    the triples: ``a``, ``b - a`` and ``c - a`` in ``wa + 2 ws`` bits."""
    return (a << (2 * ws)) | ((b - a) << ws) | (c - a)


def _mix64(h):
    """SplitMix64's finalizer on uint64 (wrapping): a well-spread 64-bit hash."""
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def _tet_face_keys(tets, n_vertices):
    """``(keys (4m,) int64, pairs)``: a key per tet face ``4 t + i`` (face
    ``i`` of tet ``t``), equal for faces with the same vertices ``a < b < c``.

    Exact where it fits in :data:`KEY_BITS`: ``a``, ``b - a`` and ``c - a``
    packed (the spans ``c - a`` are small in meshes whose vertices are
    numbered with any locality: 16 bits for a 180^3 grid), ordered as the
    triples are, and ``pairs`` None. Otherwise the key is ``mix(mix(b, c) +
    a)`` (SplitMix64's finalizer, a bijection of 64-bit words) and ``pairs``
    the exact ``(b, c)`` packed: two faces with equal keys and equal
    ``pairs`` have equal ``a`` too, so that equal keys are confirmed by
    ``pairs`` alone (:func:`_match_faces`). Computed column by column: no
    (4m, 3) array."""
    m = len(tets)
    cols = [np.ascontiguousarray(tets[:, k]) for k in range(4)]     # 32-bit where tets are
    faces = [[cols[k] for k in f] for f in FACES]
    span = max((int((np.maximum(np.maximum(x, y), z) - np.minimum(np.minimum(x, y), z)).max())
                for x, y, z in faces), default=0) if m else 0
    widths = _key_widths(n_vertices, span)
    exact = widths is not None
    keys = np.empty((m, 4), np.int64)
    pairs = None if exact else np.empty((m, 4), np.int64)
    with np.errstate(over="ignore"):
        for i, f in enumerate(faces):
            a, b, c = _sorted3(*f)
            if exact:                     # (the spans in the index type, a in 64 bits)
                ws = widths[1]
                k = keys[:, i]
                np.copyto(k, a, casting="safe")
                k <<= 2 * ws
                k |= (b - a).astype(np.int64) << ws
                k |= c - a
            else:
                a, b, c = (x.astype(np.int64, copy=False) for x in (a, b, c))
                pairs[:, i] = (b << 32) | c
                keys[:, i] = _mix64(_mix64(pairs[:, i].view(np.uint64)) + a.astype(np.uint64)
                                    ).view(np.int64)
    return keys.ravel(), None if exact else pairs.ravel()


def _tet_face_parity(tets):
    """(4m,) bool: :func:`_face_parity` of every tet face ``4 t + i`` without
    gathering it. Face ``i`` preceded by vertex ``i`` is an even permutation of
    the tet (:data:`FACES`), so its parity is the tet's plus the rank of
    vertex ``i`` among the four."""
    cols = [tets[:, k] for k in range(4)]
    inversions = sum((cols[j] > cols[k]).astype(np.int8) for j in range(4) for k in range(j + 1, 4))
    out = np.empty((len(tets), 4), bool)
    for i in range(4):
        rank = sum((cols[k] < cols[i]).astype(np.int8) for k in range(4) if k != i)
        out[:, i] = (inversions + rank) % 2 == 0
    return out.ravel()


def _face_vertices(tets, f):
    """(k, 3) vertices of the tet faces ``f`` (flat indices ``4 t + i``), as
    wound by :data:`FACES`."""
    return np.take_along_axis(tets[f // 4], FACES[f % 4], axis=1)


def unique_edges(tets):
    """(e, 2) int64: every edge of the tets once, as sorted vertex pairs."""
    t = np.asarray(tets, np.int64)
    if t.size == 0:
        return np.zeros((0, 2), np.int64)
    e = t[:, EDGES].reshape(-1, 2)
    lo, hi = np.minimum(e[:, 0], e[:, 1]), np.maximum(e[:, 0], e[:, 1])
    # one int64 key per pair, sorted and the repeats dropped: NumPy 2.4's np.unique of rows
    # (axis=0) or of bare values (hashed) takes 60x as long (6 s for 900k tets)
    n = int(hi.max()) + 1
    key = np.sort(lo * n + hi)
    key = key[np.concatenate([[True], key[1:] != key[:-1]])]
    return np.stack([key // n, key % n], axis=1)


def _edge_vectors(vertices, tets):
    """(m, 6, 3) float64: ``p_i - p_j`` for each local edge ``(i, j)`` of :data:`EDGES`."""
    v, t = np.asarray(vertices, dtype=np.float64), np.asarray(tets)
    return v[t[:, EDGES[:, 0]]] - v[t[:, EDGES[:, 1]]]


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


def longest_edges(vertices, tets):
    """(m,) float64: the longest edge of each tet (in chunks: no (m, 6, 3) array)."""
    return _tet_geometry(vertices, tets, "longest")[1]


def bounding_radius(points) -> float:
    """Half the diagonal of the box around ``points`` (k, 3) (a (2, 3) box
    itself works too): the unit in which a scalar mesh's transfer-function
    opacity is given (``opacity_scale`` per mesh radius)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    return float(np.linalg.norm(p.max(0) - p.min(0))) / 2


def mean_edge_length(vertices, tets) -> float:
    """Mean of :func:`edge_lengths` over all tets and their six edges (an
    edge shared by ``k`` tets counts ``k`` times): the mesh's cell size.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int

    Returns
    -------
    float
    """
    return float(_tet_geometry(vertices, tets, "mean")[1].mean())


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
        NaN for a tet whose four vertices coincide.
    """
    v, l2 = _tet_geometry(vertices, tets, "mean_square")
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 6.0 * np.sqrt(2.0) * v / np.maximum(l2, 1e-300) ** 1.5
    return q


def validate_arrays(vertices, tets, *, strict=True, allow_empty=False, duplicates=True):
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
    duplicates : bool
        With ``strict``, look for duplicate tets (False: the caller's face
        matching finds them, :func:`build_topology`).

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
        if duplicates:                    # (the rows sorted, for both checks)
            s = np.sort(tets, axis=1)
            repeated = np.any(s[:, 1:] == s[:, :-1], axis=1)
        else:                             # (the six pairs of columns: no sort)
            cols = [tets[:, k] for k in range(4)]
            repeated = np.zeros(len(tets), bool)
            for j, k in itertools.combinations(range(4), 2):
                repeated |= cols[j] == cols[k]
        bad = np.flatnonzero(repeated)
        if len(bad):
            raise MeshError(f"tets with a repeated vertex index: {_preview(bad)}; {REPAIR_HINT}")
        if duplicates:
            _duplicate_tets(s)
    return vertices, tets


def _duplicate_tets(s):
    """Raise :class:`MeshError` naming the tets that repeat another's four
    vertices; ``s`` (m, 4) the tets with sorted rows. One sort of a 64-bit
    hash of each row finds the candidates; the exact rows confirm them."""
    if len(s) < 2:
        return
    with np.errstate(over="ignore"):      # a wrapping linear form of the row, then one mix
        h = s[:, 3].astype(np.uint64)
        for k, factor in zip(range(3), (0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F,
                                        0x165667B19E3779F9)):
            h += s[:, k].astype(np.uint64) * np.uint64(factor)
        h = _mix64(h)
    hs = np.sort(h)
    if not np.any(hs[1:] == hs[:-1]):
        return
    candidates = np.flatnonzero(np.isin(h, hs[1:][hs[1:] == hs[:-1]]))
    _, inv, counts = np.unique(s[candidates], axis=0, return_inverse=True, return_counts=True)
    bad = candidates[counts[inv.ravel()] > 1]
    if len(bad):
        raise MeshError(f"duplicate tets (same four vertices): {_preview(bad)}; "
                        f"{REPAIR_HINT}")


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
    rotation starting at its smallest index is increasing (an even permutation
    of the sorted triple)."""
    x, y, z = tri[:, 0], tri[:, 1], tri[:, 2]
    return ((x > y).astype(np.int8) + (x > z) + (y > z)) % 2 == 0


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


def _face_pairs(faces):
    """Group equal triangles (any vertex order): ``(inv, counts, fa, fb)``
    with ``inv`` each face's group, ``counts`` each group's size and
    ``fa, fb`` the two faces of each group of two (``fa < fb``)."""
    _, inv, counts = np.unique(face_keys(faces), return_inverse=True, return_counts=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    sorted_inv = inv[order]
    start = np.flatnonzero(np.r_[True, sorted_inv[1:] != sorted_inv[:-1]])
    paired = start[counts[sorted_inv[start]] == 2]
    return inv, counts, order[paired], order[paired + 1]


def _shared_faces(tets):
    """Raise :class:`MeshError` for faces shared by more than two tets."""
    inv, counts, _, _ = _face_pairs(tets[:, FACES].reshape(-1, 3))
    if np.any(counts > 2):
        bad_keys = np.flatnonzero(counts > 2)
        bad = np.flatnonzero(np.isin(inv, bad_keys)) // 4
        raise MeshError(
            f"{len(bad_keys)} face(s) shared by more than two tets (non-manifold mesh); "
            f"tets involved: {_preview(np.unique(bad))}; {REPAIR_HINT}")


def _match_faces(tets, n_vertices):
    """Pair up the faces of oriented tets by one sort of their keys.

    Returns ``(neighbors (4m,), neighbor_faces (4m,), fa, fb)``: the tet and
    local face across each flat face index ``4 t + i`` (-1 on the boundary),
    and the flat face indices of each interior pair (``fa < fb``, pairs in
    the order of their keys). A face shared by more than two tets raises
    :class:`MeshError` (duplicate tets first, :func:`_duplicate_tets`)."""
    m = len(tets)
    keys, pairs = _tet_face_keys(tets, n_vertices)
    # (stable: Timsort finds the runs that a mesh numbered with locality has, twice as
    # fast as the default on 50M keys of a grid, and the order is deterministic)
    order = np.argsort(keys, kind="stable").astype(np.int32 if 4 * m < 2 ** 31 else np.int64)
    sk = keys[order]
    del keys
    eq = sk[1:] == sk[:-1]
    del sk
    collided = False
    if np.any(eq[1:] & eq[:-1]):           # three equal keys
        _duplicate_tets(np.sort(tets, axis=1))
        _shared_faces(tets)                # raises, unless hashes collided
        collided = True
    first = np.flatnonzero(eq)
    fa, fb = order[first], order[first + 1]
    del order, eq, first
    if pairs is not None and not collided:  # equal hashes: the same triangle, unless they collide
        collided = not np.array_equal(pairs[fa], pairs[fb])
    del pairs
    if collided:                           # the exact (slower) grouping
        _, _, fa, fb = _face_pairs(tets[:, FACES].reshape(-1, 3))
    fa, fb = np.minimum(fa, fb), np.maximum(fa, fb)
    neighbors = np.full(m * 4, -1, dtype=np.int32)
    neighbor_faces = np.full(m * 4, -1, dtype=np.int8)
    neighbors[fa], neighbors[fb] = fb // 4, fa // 4
    neighbor_faces[fa], neighbor_faces[fb] = fb % 4, fa % 4
    return neighbors, neighbor_faces, fa, fb


def _edge_adjacency(tris):
    """(b, 3): triangle across the edge opposite each corner, -1 if none."""
    b = len(tris)
    adj = np.full((b, 3), -1, dtype=np.int64)
    if b == 0:
        return adj.astype(np.int32)
    e = np.stack([tris[:, [1, 2]], tris[:, [2, 0]], tris[:, [0, 1]]], 1).reshape(-1, 2)
    e = np.sort(e, axis=1).astype(np.int64)
    key = e[:, 0] * (int(tris.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    k = key[order]
    same = np.flatnonzero(k[1:] == k[:-1])
    a, c = order[same], order[same + 1]
    adj.ravel()[a] = c // 3
    adj.ravel()[c] = a // 3
    return adj.astype(np.int32)


#: The relative tolerance of :func:`convex_boundary`'s test of an edge (the
#: sine of the angle by which it may bend inwards): a few float32 roundings of
#: the positions the renderer walks (the midpoint of a boundary edge, a rotated
#: box), no more. A ray that left through such an edge could come back only
#: within about this fraction of a face's size of the surface, where the
#: walk of a mesh that is not convex does not look either (it traces again
#: from ``retrace_epsilon`` = 1e-5 of the scene's size past the exit).
CONVEX_RTOL = 1e-6


def convex_boundary(vertices, faces, adjacency) -> bool:
    """Whether the boundary surface ``faces`` ((b, 3), wound outwards) of a
    tet mesh bounds a convex body: a closed surface (every edge in two
    faces) none of whose edges bends inwards (across each edge, the other
    face's third vertex lies on or below the face's plane, to
    :data:`CONVEX_RTOL`), and one piece. A closed connected surface that is
    convex at every edge bounds a convex body (Tietze's theorem), so a line
    crosses it at most twice: a ray that leaves the mesh does not come back.
    Each piece of such a surface is a sphere (Euler characteristic 2), and
    two convex pieces meet at one vertex at most, so the surface is one
    piece exactly where ``vertices - edges + faces`` is 2.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (b, 3) int
    adjacency : (b, 3) int
        The face across the edge opposite each corner
        (:attr:`Topology.boundary_adjacency`).
    """
    faces = np.asarray(faces, np.int64)
    adjacency = np.asarray(adjacency, np.int64)
    if len(faces) < 4 or (adjacency < 0).any():
        return False
    edges = np.sort(np.concatenate([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]]), 1)
    _, counts = np.unique(edges[:, 0] * (int(faces.max()) + 1) + edges[:, 1],
                          return_counts=True)
    if (counts != 2).any():
        return False
    V = np.asarray(vertices, np.float64)
    A, B, C = V[faces[:, 0]], V[faces[:, 1]], V[faces[:, 2]]
    n = np.cross(B - A, C - A)
    n_len = np.linalg.norm(n, axis=1)
    total = faces.sum(1)
    for j in range(3):
        across = adjacency[:, j]
        # (closed: the face across shares the edge opposite corner j)
        W = V[total[across] - (total - faces[:, j])]
        side = np.einsum("ij,ij->i", n, W - A)
        if (side > CONVEX_RTOL * n_len * np.linalg.norm(W - A, axis=1)).any():
            return False
    return len(np.unique(faces)) - len(counts) + len(faces) == 2


#: Meshes of at least this many tets show the topology's progress (a few seconds).
PROGRESS_TETS = 4_000_000


def build_topology(vertices, tets, *, warn=True, check=True, progress=None) -> Topology:
    """Orient tets, match faces, find the boundary.

    Time and memory linear in the mesh but for one sort of a 64-bit key per
    face: about 135 bytes per tet at the peak (the result, 47 of them,
    included) beside the input.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    warn : bool
        Emit warnings for repaired input (inverted or flat tets).
    check : bool
        Validate the arrays first (:func:`validate_arrays`); False for
        arrays validated already (a :class:`~mi_tetvr.mesh.TetMesh`'s).
    progress : bool, optional
        A progress bar of its steps on stderr (default: for meshes of
        :data:`PROGRESS_TETS` tets or more).

    Returns
    -------
    Topology

    Raises
    ------
    MeshError
        Bad indices, non-finite positions, duplicate tets or faces shared by
        more than two tets.
    """
    from mi_tetvr.progress import progress_bar
    m = len(tets)
    with progress_bar(total=4, desc=f"topology of {m:,} tets", unit="step",
                      disable=not (m >= PROGRESS_TETS if progress is None else progress)) as bar:
        return _build_topology(vertices, tets, warn, check, bar)


def _build_topology(vertices, tets, warn, check, bar) -> Topology:
    """:func:`build_topology`, its steps counted on ``bar``."""
    m = len(tets)
    if check:   # duplicates show in the face matching: looked for only then
        vertices, tets = validate_arrays(vertices, tets, duplicates=False)
    bar.update()
    vertices = np.asarray(vertices, np.float64)
    tets = np.asarray(tets).astype(np.int32 if len(vertices) < 2 ** 31 else np.int64)
    tets, vol, flip, flat = orient_tets(vertices, tets)
    bar.update()
    neighbors, neighbor_faces, fa, fb = _match_faces(tets, len(vertices))
    bar.update()
    parity = _tet_face_parity(tets)
    pa, pb = parity[fa], parity[fb]

    # Flat tets have no geometric orientation: orient them so that the faces
    # they share with oriented neighbours appear with opposite winding.
    oriented = ~flat
    while flat.any():
        ta, tb = fa // 4, fb // 4
        bad = pa == pb
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
            neighbors, neighbor_faces, fa, fb = _match_faces(tets, len(vertices))
            parity = _tet_face_parity(tets)
            pa, pb = parity[fa], parity[fb]

    inconsistent = pa == pb
    bar.update()
    if inconsistent.any():
        _duplicate_tets(np.sort(tets, axis=1))
        raise MeshError(
            f"{int(np.count_nonzero(inconsistent))} interior face(s) are not shared with "
            f"opposite orientation even after orienting every tet: the mesh folds over itself "
            f"(tets {_preview(np.unique(fa[inconsistent] // 4))}); {REPAIR_HINT}")
    del pa, pb, fa, fb, inconsistent, parity
    n_flipped = int(np.count_nonzero(flip))
    n_flat = int(np.count_nonzero(flat))
    if warn and n_flipped:
        warnings.warn(f"{n_flipped} inverted tet(s) re-oriented", stacklevel=3)
    if warn and n_flat:
        warnings.warn(
            f"{n_flat} zero-volume tet(s) kept (they contribute nothing; rays step "
            f"over them): {_preview(np.flatnonzero(flat))}", stacklevel=3)
    bnd = np.flatnonzero(neighbors < 0)
    bfaces = _face_vertices(tets, bnd)
    return Topology(
        tets=tets.astype(np.int32, copy=False),
        neighbors=neighbors.reshape(m, 4),
        neighbor_faces=neighbor_faces.reshape(m, 4),
        boundary_faces=bfaces.astype(np.int32),
        boundary_adjacency=_edge_adjacency(bfaces),
        boundary_tets=(bnd // 4).astype(np.int32),
        boundary_local_faces=(bnd % 4).astype(np.int8),
        volumes=np.abs(vol),
        flat=flat,
        n_flipped=n_flipped,
    )


def _bad_faces_per_tet(tets):
    """(m,) number of faces of each oriented tet that are shared by more than
    two tets or with the same orientation as its neighbour's (a fold)."""
    m = len(tets)
    faces = tets[:, FACES].reshape(-1, 3)
    inv, counts, fa, fb = _face_pairs(faces)
    bad = counts[inv] > 2
    par = _face_parity(faces)
    same = par[fa] == par[fb]
    bad[fa[same]] = bad[fb[same]] = True
    return bad.reshape(m, 4).sum(axis=1), (fa[same], fb[same])


def repair_tets(vertices, tets, flat_tol=FLAT_TOLERANCE, max_rounds=50):
    """The tets to drop so that a mesh can be rendered, and why.

    Dropped, in this order: tets with a repeated vertex; duplicates (the
    first of each set stays); flat tets (:func:`orient_tets`); and folded
    tets, which overlap their neighbours so that after orienting every tet a
    shared face has the same orientation on both sides (or a face is shared
    by more than two tets). Folded tets are removed greedily: each round the
    tets with the most such faces go (an inverted tet inside a mesh has all
    four); where every offender has one, the worse-shaped tet of each pair.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int

    Returns
    -------
    keep : (m,) bool
    report : dict
        ``repeated_vertex``, ``duplicate``, ``flat``, ``folded``: indices of
        the dropped tets (into ``tets``); ``boundary_faces``: ``[before,
        after]``, the faces that belong to one tet only (a dropped interior tet
        opens a hole whose faces count).
    """
    v = np.asarray(vertices, np.float64)
    t = np.asarray(tets, np.int64).reshape(-1, 4)
    m = len(t)
    s = np.sort(t, axis=1)
    repeated = np.any(s[:, 1:] == s[:, :-1], axis=1)
    keep = ~repeated
    _, first = np.unique(s, axis=0, return_index=True)
    unique = np.zeros(m, bool)
    unique[first] = True
    duplicate = keep & ~unique
    keep &= unique
    flat = keep & orient_tets(v, t, flat_tol).flat
    keep &= ~flat
    folded = []
    for _ in range(max_rounds):
        idx = np.flatnonzero(keep)
        oriented = orient_tets(v, t[idx], flat_tol).tets
        count, (fa, fb) = _bad_faces_per_tet(oriented)
        if not count.any():
            break
        if count.max() > 1:
            drop = idx[count == count.max()]
        else:   # the worse of each folded pair, and the tets of over-shared faces
            q = np.abs(quality(v, oriented))
            worse = np.where(q[fa // 4] <= q[fb // 4], fa // 4, fb // 4)
            shared = np.setdiff1d(np.flatnonzero(count), np.r_[fa, fb] // 4)
            drop = idx[np.union1d(worse, shared)]
        folded.append(drop)
        keep[drop] = False

    def boundary(tt):
        _, c = np.unique(face_keys(tt[:, FACES].reshape(-1, 3)), return_counts=True)
        return int(np.count_nonzero(c == 1))

    return keep, {"repeated_vertex": np.flatnonzero(repeated).tolist(),
                  "duplicate": np.flatnonzero(duplicate).tolist(),
                  "flat": np.flatnonzero(flat).tolist(),
                  "folded": np.sort(np.concatenate(folded)).tolist() if folded else [],
                  "boundary_faces": [boundary(t[~repeated]), boundary(t[keep])]}


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
        "slivers": int(np.count_nonzero((q < SLIVER_QUALITY) & ~topology.flat)),
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
