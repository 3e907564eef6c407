"""Initial tetrahedral meshes for reconstruction, over the region that matters.

Free functions over numpy arrays. Every initializer returns
``(vertices (n, 3) float64, tets (m, 4) int64)`` with positively oriented tets
(``det(p1 - p0, p2 - p0, p3 - p0) > 0``, the convention of
:mod:`mi_tetvr.mesh.topology`), no zero-volume tets and no unreferenced vertices.

* :func:`grid_init` -- a regular grid of near-cubic cells over a box, 6 tets
  per cell (:func:`mi_tetvr.mesh.generate.grid_mesh`).
* :func:`tetwild_init` -- fTetWild (through ``pytetwild``) on a box or on a
  closed surface.
* :func:`delaunay_init` -- Delaunay tetrahedralization of sparse points (e.g.
  COLMAP's), after statistical outlier removal.
* :func:`unbounded_init` -- a whole unbounded scene: the Delaunay
  tetrahedralization of sparse points together with points on far shells
  around the cameras, so that every camera is inside the mesh and cells grow
  with the distance (as Radiance Meshes and Radiant Foam start).

The box they fill comes from the data: :mod:`mi_tetvr.recon.hull` (visual
hull of alpha masks, what the cameras see) or
:meth:`mi_tetvr.recon.datasets.Dataset.bounds`.
"""
from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

from mi_tetvr.extras import needs
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import FLAT_TOLERANCE, MeshError, check_bounds, orient_tets

__all__ = ["grid_init", "grid_shape", "grid_sample", "tetwild_init", "delaunay_init", "box_surface",
           "remove_outliers", "unbounded_init", "shell_points",
           "orient_and_compact", "retriangulate"]


# --------------------------------------------------------------------------- helpers
def orient_and_compact(vertices, tets, flat_tol=None):
    """Orient tets positively (:func:`~mi_tetvr.mesh.orient_tets`), optionally
    drop (near-)flat ones, and drop unreferenced vertices.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    flat_tol : float, optional
        Tets flat by this tolerance (:func:`~mi_tetvr.mesh.orient_tets`) are
        removed. ``None`` keeps every tet.

    Returns
    -------
    vertices : (n', 3) float64
    tets : (m', 4) int64
        Positively oriented, indexing only the vertices kept, each of which is
        referenced by at least one tet.
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    if flat_tol is None:
        t = orient_tets(v, t, 0.0).tets
    else:
        oriented = orient_tets(v, t, flat_tol)
        t = oriented.tets[~oriented.flat]
    used, inv = np.unique(t, return_inverse=True)
    return v[used].copy(), inv.reshape(-1, 4).astype(np.int64)


# --------------------------------------------------------------------------- grid
def grid_init(bounds, resolution: int, jitter: float = 0.0, seed: int = 0):
    """A regular tet grid over an axis-aligned box, 6 tets per near-cubic cell.

    Parameters
    ----------
    bounds : (2, 3) float
        Min and max corner of the box.
    resolution : int
        Number of cells along the box's largest axis; every other axis gets
        ``max(1, round(resolution * extent / largest_extent))`` cells.
    jitter : float
        Interior vertices move uniformly by up to ``jitter`` times the cell
        size per axis (< 0.5 keeps every tet positively oriented); boundary
        vertices stay, so the box is covered exactly.
    seed : int
        Seed of the jitter.

    Returns
    -------
    vertices : (n, 3) float64
    tets : (6 nx ny nz, 4) int64
        Kuhn split of each cell (:data:`mi_tetvr.mesh.generate.KUHN_TETS`).
    """
    if not 0.0 <= jitter < 0.5:
        raise ValueError(f"jitter must be in [0, 0.5), got {jitter}")
    b = check_bounds(bounds)
    v, t = grid_mesh(grid_shape(b, resolution), b[0], b[1], jitter=jitter, seed=seed)
    return v.astype(np.float64), t.astype(np.int64)


def grid_shape(bounds, resolution: int):
    """Cells per axis of :func:`grid_init`'s grid: ``resolution`` along the
    box's largest axis, ``max(1, round(resolution * extent / largest))`` along
    the others."""
    b = check_bounds(bounds)
    resolution = int(resolution)
    if resolution < 1:
        raise ValueError(f"resolution must be >= 1, got {resolution}")
    ext = b[1] - b[0]
    return tuple(int(max(1, round(resolution * e / ext.max()))) for e in ext)


def grid_sample(bounds, resolution: int, values, points):
    """The piecewise-linear field of an (unjittered) :func:`grid_init` mesh at
    arbitrary points: what a coarse grid's vertex values give a finer mesh.

    Each cell's 6 Kuhn tets are the 6 orderings of the local coordinates
    (Freudenthal), so a point's tet and barycentric weights follow from
    sorting its coordinates in the cell. Points outside the box take the
    value at the nearest point of the box.

    Parameters
    ----------
    bounds, resolution
        As given to :func:`grid_init`.
    values : (n, ...) array
        Per-vertex values in :func:`grid_init`'s vertex order.
    points : (p, 3) float

    Returns
    -------
    (p, ...) float64
    """
    b = check_bounds(bounds)
    shape = np.asarray(grid_shape(b, resolution))
    values = np.asarray(values, np.float64)
    if len(values) != np.prod(shape + 1):
        raise ValueError(f"{len(values)} values for a grid of {tuple(shape)} cells "
                         f"({np.prod(shape + 1)} vertices)")
    t = (np.asarray(points, np.float64).reshape(-1, 3) - b[0]) / (b[1] - b[0]) * shape
    t = np.clip(t, 0.0, shape)
    cell = np.minimum(np.floor(t), shape - 1).astype(np.int64)
    f = t - cell
    order = np.argsort(-f, axis=1, kind="stable")          # the path from corner 0 to 7
    fs = np.take_along_axis(f, order, axis=1)
    weights = np.column_stack([1.0 - fs[:, 0], fs[:, 0] - fs[:, 1], fs[:, 1] - fs[:, 2], fs[:, 2]])
    stride = np.array([(shape[1] + 1) * (shape[2] + 1), shape[2] + 1, 1])
    index = cell @ stride
    out = weights[:, 0, None] * values[index].reshape(len(index), -1)
    for k in range(3):
        index = index + stride[order[:, k]]
        out += weights[:, k + 1, None] * values[index].reshape(len(index), -1)
    return out.reshape((len(index),) + values.shape[1:])


# --------------------------------------------------------------------------- fTetWild
def box_surface(bounds):
    """Closed, outward-oriented triangle surface of an axis-aligned box.

    Parameters
    ----------
    bounds : (2, 3) float

    Returns
    -------
    trimesh.Trimesh
        8 vertices, 12 faces.
    """
    with needs("recon", "reading a surface mesh"):
        import trimesh

    return trimesh.creation.box(bounds=check_bounds(bounds))


def _load_surface(surface):
    with needs("recon", "reading a surface mesh"):
        import trimesh

    if isinstance(surface, (str, Path)):
        path = Path(surface)
        if not path.exists():
            raise FileNotFoundError(f"surface file not found: {path}")
        surface = trimesh.load(path, force="mesh")
    if isinstance(surface, trimesh.Scene):
        surface = (surface.to_geometry() if hasattr(surface, "to_geometry")
                   else surface.dump(concatenate=True))
    if not isinstance(surface, trimesh.Trimesh):
        raise TypeError(f"surface must be a trimesh.Trimesh or a path trimesh loads, "
                        f"got {type(surface).__name__}")
    if len(surface.faces) == 0:
        raise MeshError("the surface has no triangles")
    return surface


def tetwild_init(surface=None, bounds=None, edge_length_fac: float = 0.1,
                 edge_length_abs: float | None = None, *, optimize: bool = True,
                 simplify: bool = True, epsilon: float = 1e-3, stop_energy: float = 10.0,
                 coarsen: bool = False, num_opt_iter: int = 80, num_threads: int = 0,
                 quiet: bool = True):
    """Tetrahedralize a box or a closed surface with fTetWild (``pytetwild``).

    Parameters
    ----------
    surface : trimesh.Trimesh or str or Path, optional
        Surface to fill (a path is loaded with ``trimesh.load``). Exactly one
        of ``surface`` and ``bounds`` must be given.
    bounds : (2, 3) float, optional
        Box to fill instead of a surface.
    edge_length_fac : float
        Target edge length as a fraction of the input's bounding-box diagonal
        (fTetWild's ``-l``); ignored when ``edge_length_abs`` is given.
    edge_length_abs : float, optional
        Absolute target edge length.
    optimize : bool
        Run fTetWild's quality optimization (slower, better tets).
    simplify : bool
        Let fTetWild simplify the input surface first.
    epsilon : float
        Envelope size: the most the output boundary may deviate from the
        input surface, relative to the bounding-box diagonal (``-e``).
    stop_energy : float
        Optimization stops when the AMIPS energy reaches this (``--stop-energy``).
    coarsen : bool
        Coarsen the output as much as quality allows.
    num_opt_iter : int
        Maximum optimization iterations.
    num_threads : int
        Threads (0: all cores).
    quiet : bool
        Silence fTetWild's log.

    Returns
    -------
    vertices : (n, 3) float64
    tets : (m, 4) int64
        Positively oriented, every vertex referenced. (fTetWild emits tets of
        the opposite orientation; they are flipped here.)

    Notes
    -----
    fTetWild writes a ``__tracked_surface.stl`` into the working directory;
    it runs here in a temporary directory (``os.chdir``, so not from several
    threads at once).
    """
    if (surface is None) == (bounds is None):
        raise ValueError("give exactly one of `surface` and `bounds`")
    if not 0.0 < edge_length_fac <= 1.0:
        raise ValueError(f"edge_length_fac must be in (0, 1], got {edge_length_fac}")
    if edge_length_abs is not None and not edge_length_abs > 0:
        raise ValueError(f"edge_length_abs must be > 0, got {edge_length_abs}")
    surf = box_surface(bounds) if surface is None else _load_surface(surface)
    with needs("recon", "fTetWild's mesh"):
        import pytetwild  # imports pyvista at import time
    # fTetWild writes `__tracked_surface.stl` into the working directory: run
    # it in a scratch one (the surface is already loaded)
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="mi_tetvr_tetwild_") as scratch:
        os.chdir(scratch)
        try:
            v, t = pytetwild.tetrahedralize(
                np.ascontiguousarray(surf.vertices, dtype=np.float64),
                np.ascontiguousarray(surf.faces, dtype=np.int32),
                edge_length_fac=edge_length_fac, edge_length_abs=edge_length_abs,
                optimize=optimize, simplify=simplify, epsilon=epsilon,
                stop_energy=stop_energy, coarsen=coarsen, num_threads=num_threads,
                num_opt_iter=num_opt_iter, quiet=quiet)
        finally:
            os.chdir(cwd)
    t = np.asarray(t, dtype=np.int64).reshape(-1, 4)
    if len(t) == 0:
        raise MeshError("fTetWild produced no tetrahedra (is the surface closed?)")
    return orient_and_compact(v, t, flat_tol=FLAT_TOLERANCE)


# --------------------------------------------------------------------------- Delaunay
def remove_outliers(points, outlier_std: float = 2.0, k_neighbors: int = 8):
    """Statistical outlier removal.

    A point is an outlier when its mean distance to its ``k_neighbors``
    nearest neighbours exceeds the mean of that quantity over all points by
    more than ``outlier_std`` standard deviations.

    Parameters
    ----------
    points : (k, 3) float
    outlier_std : float
    k_neighbors : int

    Returns
    -------
    (k,) bool
        True for the points kept.
    """
    with needs("recon", "a Delaunay mesh of points"):
        from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    k = min(int(k_neighbors), len(p) - 1)
    if k < 1:
        return np.ones(len(p), bool)
    d, _ = cKDTree(p).query(p, k=k + 1)
    md = d[:, 1:].mean(axis=1)
    return md <= md.mean() + outlier_std * md.std()


def _delaunay_tets(p, flat_tol, joggle, seed, caller):
    """Delaunay tets of the points ``p`` (k, 3), the vertices of flat tets joggled and the
    triangulation redone (see :func:`delaunay_init`); returns the (joggled) points and the
    tets without the flat ones still left (warned about)."""
    with needs("recon", "a Delaunay mesh of points"):
        from scipy.spatial import Delaunay, QhullError, cKDTree
    rng = np.random.default_rng(seed)
    nn = None
    for attempt in range(5):
        try:
            tri = Delaunay(p)
        except QhullError as e:
            raise MeshError(f"Delaunay failed (points coplanar or degenerate?): {e}") from e
        t = tri.simplices.astype(np.int64)
        flat = orient_tets(p, t, flat_tol).flat
        if not flat.any() or attempt == 4:
            break
        if nn is None:
            nn = cKDTree(p).query(p, k=2)[0][:, 1]
        moved = np.unique(t[flat])
        p = p.copy()
        p[moved] += rng.uniform(-1, 1, (len(moved), 3)) * (joggle * 10 ** attempt) * nn[moved, None]
    if flat.any():
        warnings.warn(f"{caller}: {int(flat.sum())} flat tet(s) dropped after joggling; "
                      "the mesh may have internal boundary faces", stacklevel=3)
    return p, t[~flat]


def delaunay_init(points, outlier_std: float | None = 2.0, k_neighbors: int = 8,
                  min_points: int = 20, padding: float | None = None,
                  flat_tol: float = FLAT_TOLERANCE, joggle: float = 1e-4, seed: int = 0):
    """Delaunay tetrahedralization of sparse points (e.g. a COLMAP cloud).

    Parameters
    ----------
    points : (k, 3) float
    outlier_std : float or None
        Statistical outlier removal threshold (see :func:`remove_outliers`);
        ``None`` keeps every point.
    k_neighbors : int
        Neighbours used by the outlier statistics.
    min_points : int
        Clouds with fewer points skip outlier removal (too few for
        meaningful statistics).
    padding : float, optional
        When given, the 8 corners of the points' bounding box, enlarged by
        ``padding`` times its extent on every side, are added so that the
        hull covers the whole region.
    flat_tol : float
        A tet is flat when ``|volume| <= flat_tol * l**3``, ``l`` its longest
        edge (:func:`~mi_tetvr.mesh.orient_tets`).
    joggle : float
        Delaunay of coplanar / cospherical points (lattices, box corners)
        yields flat tets. Simply deleting an interior flat tet would leave
        the mesh non-conforming (the flat tet glues two differently
        triangulated quads), so instead the vertices of flat tets are moved
        by up to ``joggle`` times their nearest-neighbour distance and the
        triangulation is redone (up to 4 times, the joggle growing 10x each
        time); the returned vertices carry that perturbation. Flat tets that
        still remain are dropped, with a warning.
    seed : int
        Seed of the joggle.

    Returns
    -------
    vertices : (n, 3) float64
        A subset of the (deduplicated, inlier) points, plus the box corners.
        Every vertex is referenced.
    tets : (m, 4) int64
        Positively oriented, no flat tet, conforming.

    Raises
    ------
    MeshError
        Fewer than 4 points in general position remain.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (k, 3), got {p.shape}")
    p = p[np.all(np.isfinite(p), axis=1)]
    p = np.unique(p, axis=0)
    if outlier_std is not None and len(p) >= max(int(min_points), 2):
        p = p[remove_outliers(p, outlier_std, k_neighbors)]
    if padding is not None and len(p):
        lo, hi = p.min(0), p.max(0)
        ext = np.maximum(hi - lo, 1e-9 * max(float(np.ptp(p)), 1.0))
        lo, hi = lo - float(padding) * ext, hi + float(padding) * ext
        corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        p = np.unique(np.concatenate([p, corners]), axis=0)
    if len(p) < 4:
        raise MeshError(f"Delaunay needs at least 4 points, {len(p)} remain")
    p, t = _delaunay_tets(p, flat_tol, joggle, seed, "delaunay_init")
    v, t = orient_and_compact(p, t)
    if len(t) == 0:
        raise MeshError("every Delaunay tet is flat: the points are (nearly) coplanar")
    return v, t


def retriangulate(vertices, point_data=None, flat_tol: float = FLAT_TOLERANCE,
                  joggle: float = 1e-4, seed: int = 0):
    """The Delaunay tetrahedralization of a mesh's vertices where they are now (after they
    moved in a fit): the same vertices, new tets, the per-vertex data following its vertex.

    Parameters
    ----------
    vertices : (n, 3) float
    point_data : dict of (n, ...) arrays, optional
    flat_tol, joggle, seed
        As in :func:`delaunay_init` (the vertices of flat tets are joggled, by up to
        ``joggle`` times their nearest-neighbour distance).

    Returns
    -------
    vertices : (n', 3) float64
        The vertices that some tet uses (all but duplicates), in their order.
    tets : (m, 4) int64
        Positively oriented, no flat tet, conforming; their union is the vertices' convex hull.
    point_data : dict
        ``point_data``'s arrays at the vertices kept.
    parent : (n',) int64
        Each vertex's index among ``vertices``.
    """
    p = np.asarray(vertices, np.float64).reshape(-1, 3)
    if len(p) < 4 or not np.all(np.isfinite(p)):
        raise MeshError(f"retriangulate needs at least 4 finite vertices, got {len(p)}")
    p, t = _delaunay_tets(p, flat_tol, joggle, seed, "retriangulate")
    t = orient_tets(p, t, 0.0).tets
    used, inv = np.unique(t, return_inverse=True)
    data = {k: np.asarray(a)[used] for k, a in (point_data or {}).items()}
    return p[used], inv.reshape(-1, 4).astype(np.int64), data, used.astype(np.int64)


# --------------------------------------------------------------------------- unbounded
def shell_points(center, radii, per_shell: int, seed: int = 0):
    """Points on concentric spheres: ``per_shell`` on each (a Fibonacci
    lattice, randomly rotated per shell so that shells do not line up).

    Parameters
    ----------
    center : (3,) float
    radii : (s,) float
    per_shell : int
    seed : int

    Returns
    -------
    (s * per_shell, 3) float64
    """
    with needs("recon", "an initial mesh of an unbounded scene"):
        from scipy.spatial.transform import Rotation
    i = np.arange(per_shell) + 0.5
    z = 1.0 - 2.0 * i / per_shell
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    r = np.sqrt(1.0 - z * z)
    unit = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    rotations = Rotation.random(len(radii), random_state=seed).as_matrix()
    return np.concatenate([np.asarray(center, np.float64) + rad * unit @ rot.T
                           for rad, rot in zip(np.asarray(radii, np.float64), rotations)])


def contracted_grid_points(center, r0: float, far: float, count: int, seed: int = 0):
    """About ``count`` points between the radii ``r0`` and ``far * r0`` of
    ``center`` on a jittered grid in mip-NeRF 360's contracted space
    (``x / r0`` inside the unit ball, ``(2 - 1 / |x|) x / |x|`` beyond it),
    mapped back to world space: the grid cells grow with the square of the
    distance.

    Returns
    -------
    (k, 3) float64
    """
    outer = 2.0 - 1.0 / float(far)
    volume = 4.0 / 3.0 * np.pi * (outer ** 3 - 1.0)
    g = max(int(np.ceil((count * 64.0 / volume) ** (1.0 / 3.0))), 2)
    axis = (np.arange(g) + 0.5) / g * 4.0 - 2.0
    q = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    q = q + np.random.default_rng(seed).uniform(-0.2, 0.2, q.shape) * (4.0 / g)
    n = np.linalg.norm(q, axis=1)
    q, n = q[(n > 1.0) & (n < outer)], n[(n > 1.0) & (n < outer)]
    world = q / n[:, None] / (2.0 - n[:, None])          # |world| = 1 / (2 - |q|)
    return np.asarray(center, np.float64) + float(r0) * world


def unbounded_init(points, cameras, far: float = 8.0, shells: int = 6,
                   per_shell: int | None = None, outlier_std: float | None = 2.0,
                   seed: int = 0, outer: str = "shells"):
    """A mesh over a whole unbounded scene, cameras inside.

    The sparse points (statistical outliers removed, :func:`remove_outliers`)
    are tetrahedralized together with points on ``shells`` spheres around the
    scene's centre whose radii grow geometrically from just outside the
    cameras and the bulk of the points (``r0``) to ``far * r0``: every shell
    carries as many points, so the cells grow in proportion to their
    distance, as a grid in mip-NeRF 360's contracted space does. The convex
    hull is the outermost shell; a learned background lies beyond.

    Parameters
    ----------
    points : (k, 3) float
        Sparse points of the scene (e.g. structure from motion's).
    cameras : (c, 3) float
        Camera centres: the mesh contains them.
    far : float
        Radius of the outermost shell over ``r0``.
    shells : int
        Number of shells (at least 1).
    per_shell : int, optional
        Points per shell (default: the scene points over the shells, within
        200 .. 2000: as many points far away as near).
    outlier_std : float or None
        Outlier removal of the points (``None``: keep all).
    seed : int
    outer : str
        ``"shells"`` (the spheres above) or ``"contracted"`` (as many points
        on a grid in contracted space between ``r0`` and ``far * r0``,
        :func:`contracted_grid_points`).

    Returns
    -------
    vertices : (n, 3) float64
    tets : (m, 4) int64
        Positively oriented, conforming (:func:`delaunay_init`).
    is_shell : (n,) bool
        The vertices that are shell points (no point of the scene).
    """
    with needs("recon", "an initial mesh of an unbounded scene"):
        from scipy.spatial import cKDTree
    p = np.unique(np.asarray(points, np.float64).reshape(-1, 3), axis=0)
    p = p[np.all(np.isfinite(p), axis=1)]
    if outlier_std is not None and len(p) >= 20:
        p = p[remove_outliers(p, outlier_std)]
    c = np.asarray(cameras, np.float64).reshape(-1, 3)
    if len(c) == 0:
        raise ValueError("unbounded_init needs the camera centres")
    center = np.median(np.concatenate([c, p]) if len(p) else c, axis=0)
    dist = np.linalg.norm(p - center, axis=1) if len(p) else np.zeros(0)
    r_cam = float(np.linalg.norm(c - center, axis=1).max())
    r0 = 1.1 * max(r_cam, float(np.percentile(dist, 90)) if len(dist) else 0.0, 1e-6)
    p = p[dist < far * r0 * 0.95] if len(p) else p
    if per_shell is None:
        per_shell = int(np.clip(len(p) // max(int(shells), 1), 200, 2000))
    radii = r0 * float(far) ** (np.arange(max(int(shells), 1)) / max(int(shells) - 1, 1))
    if outer == "shells":
        shell = shell_points(center, radii, per_shell, seed)
    elif outer == "contracted":
        shell = contracted_grid_points(center, r0, far, len(radii) * per_shell, seed)
    else:
        raise ValueError(f"outer must be shells or contracted, got {outer!r}")
    vertices, tets = delaunay_init(np.concatenate([p, shell]), outlier_std=None, seed=seed)
    is_shell = cKDTree(shell).query(vertices)[0] < 1e-6 * radii[-1]
    return vertices, tets, is_shell
