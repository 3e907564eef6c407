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
* :func:`visual_hull_bounds` -- the box enclosing the visual hull of alpha
  masks, to give the initializers their region; :func:`project_points` is the
  pinhole projection it uses.

Camera convention (Mitsuba's ``perspective`` sensor, verified against
``Sensor.sample_ray`` in ``tests/test_initmesh.py``): camera space has +z
forward, +y up and **+x to the left** of the image; ``to_world`` maps camera
to world space. Pixel coordinates are continuous, (0, 0) is the top-left
corner of the image, x grows to the right and y downwards, and the centre of
pixel (row i, column j) is (j + 0.5, i + 0.5). Hence::

    u = cx - fx * x_cam / z_cam,    v = cy - fy * y_cam / z_cam

For a Mitsuba sensor of width W, height H and horizontal field of view
``fov`` (``fov_axis='x'``): ``fx = fy = W / (2 tan(fov / 2))``,
``cx = W (0.5 - principal_point_offset_x)`` and
``cy = H (0.5 - principal_point_offset_y)``.
"""
from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import FLAT_TOLERANCE, MeshError, signed_volumes

__all__ = ["grid_init", "tetwild_init", "delaunay_init", "box_surface",
           "remove_outliers", "project_points", "visual_hull_bounds",
           "initial_bounds_from_cameras",
           "orient_and_compact"]


# --------------------------------------------------------------------------- helpers
def _as_bounds(bounds):
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3):
        raise ValueError(f"bounds must have shape (2, 3) (min and max corner), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("bounds must be finite")
    if np.any(b[1] <= b[0]):
        raise ValueError(f"bounds must have max > min on every axis, got {b.tolist()}")
    return b


def orient_and_compact(vertices, tets, flat_tol=None):
    """Orient tets positively, optionally drop (near-)flat ones, and drop
    unreferenced vertices.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    flat_tol : float, optional
        Tets with ``|volume| <= flat_tol * diag**3`` are removed, ``diag``
        being the bounding-box diagonal of the referenced vertices. ``None``
        keeps every tet.

    Returns
    -------
    vertices : (n', 3) float64
    tets : (m', 4) int64
        Positively oriented, indexing only the vertices kept, each of which is
        referenced by at least one tet.
    """
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    vol = signed_volumes(v, t)
    if flat_tol is not None and len(t):
        used = v[np.unique(t)]
        diag = float(np.linalg.norm(np.ptp(used, axis=0))) or 1.0
        keep = np.abs(vol) > flat_tol * diag ** 3
        t, vol = t[keep], vol[keep]
    t = t.copy()
    neg = vol < 0
    t[neg] = t[neg][:, [0, 1, 3, 2]]
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
    b = _as_bounds(bounds)
    resolution = int(resolution)
    if resolution < 1:
        raise ValueError(f"resolution must be >= 1, got {resolution}")
    if not 0.0 <= jitter < 0.5:
        raise ValueError(f"jitter must be in [0, 0.5), got {jitter}")
    ext = b[1] - b[0]
    shape = tuple(int(max(1, round(resolution * e / ext.max()))) for e in ext)
    v, t = grid_mesh(shape, b[0], b[1], jitter=jitter, seed=seed)
    return v.astype(np.float64), t.astype(np.int64)


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
    import trimesh

    return trimesh.creation.box(bounds=_as_bounds(bounds))


def _load_surface(surface):
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
    try:
        import pytetwild  # imports pyvista at import time
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("tetwild_init needs `pytetwild` (and `pyvista`, which it imports): "
                          "pip install pytetwild pyvista") from e
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
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    k = min(int(k_neighbors), len(p) - 1)
    if k < 1:
        return np.ones(len(p), bool)
    d, _ = cKDTree(p).query(p, k=k + 1)
    md = d[:, 1:].mean(axis=1)
    return md <= md.mean() + outlier_std * md.std()


def delaunay_init(points, outlier_std: float | None = 2.0, k_neighbors: int = 8,
                  min_points: int = 20, padding: float | None = None,
                  flat_tol: float = 1e-11, joggle: float = 1e-4, seed: int = 0):
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
        A tet is flat when ``|volume| <= flat_tol * diag**3`` (``diag``:
        bounding-box diagonal). Default: 10 x
        :data:`mi_tetvr.mesh.FLAT_TOLERANCE`.
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
    from scipy.spatial import Delaunay, QhullError, cKDTree

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
    diag = float(np.linalg.norm(np.ptp(p, axis=0)))
    tol = flat_tol * diag ** 3
    rng = np.random.default_rng(seed)
    nn = None
    for attempt in range(5):
        try:
            tri = Delaunay(p)
        except QhullError as e:
            raise MeshError(f"Delaunay failed (points coplanar or degenerate?): {e}") from e
        t = tri.simplices.astype(np.int64)
        flat = np.abs(signed_volumes(p, t)) <= tol
        if not flat.any() or attempt == 4:
            break
        if nn is None:
            nn = cKDTree(p).query(p, k=2)[0][:, 1]
        moved = np.unique(t[flat])
        p = p.copy()
        p[moved] += rng.uniform(-1, 1, (len(moved), 3)) * (joggle * 10 ** attempt) * nn[moved, None]
    if flat.any():
        warnings.warn(f"delaunay_init: {int(flat.sum())} flat tet(s) dropped after joggling; "
                      "the mesh may have internal boundary faces", stacklevel=2)
    v, t = orient_and_compact(p, t[~flat])
    if len(t) == 0:
        raise MeshError("every Delaunay tet is flat: the points are (nearly) coplanar")
    return v, t


# --------------------------------------------------------------------------- visual hull
def project_points(points, view):
    """Project world points into a pinhole view (Mitsuba's camera convention).

    Parameters
    ----------
    points : (k, 3) float
    view : object
        With attributes ``to_world`` (4, 4) camera-to-world (Mitsuba: +z
        forward, +y up, +x to the image's left) and ``fx, fy, cx, cy`` in
        pixels.

    Returns
    -------
    uv : (k, 2) float64
        Continuous pixel coordinates (x right, y down; (0, 0) is the image's
        top-left corner; pixel centres at half-integers). NaN-free; meaningless
        where ``depth <= 0``.
    depth : (k,) float64
        ``z`` in camera space (> 0 in front of the camera).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    to_world = np.asarray(view.to_world, dtype=np.float64).reshape(4, 4)
    w2c = np.linalg.inv(to_world)
    pc = p @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    safe = np.where(np.abs(z) > 1e-300, z, 1e-300)
    u = float(view.cx) - float(view.fx) * pc[:, 0] / safe
    v = float(view.cy) - float(view.fy) * pc[:, 1] / safe
    return np.stack([u, v], axis=1), z


def _camera_centres_dirs(views):
    c, d = [], []
    for view in views:
        m = np.asarray(view.to_world, dtype=np.float64).reshape(4, 4)
        c.append(m[:3, 3])
        f = m[:3, 2]
        d.append(f / np.linalg.norm(f))
    return np.array(c), np.array(d)


def _image_size(view):
    img = getattr(view, "image", None)
    if img is not None:
        return int(np.shape(img)[1]), int(np.shape(img)[0])
    return int(view.width), int(view.height)


def initial_bounds_from_cameras(views):
    """A generous box for the visual hull, from the cameras alone.

    Assumes object-centric views (cameras looking at a common target and
    seeing all of the object). The centre is the point closest (least
    squares) to all optical axes; the half-size is the half-extent that
    every image covers at the nearest camera's distance,
    ``min_i D_i * min_i(cx / fx, (W - cx) / fx, cy / fy, (H - cy) / fy)``,
    so that (with ``outside='keep'``) most of the box is seen, and can be
    carved, by every view. For
    forward-facing captures (near-parallel axes) the centre is put ahead of
    the cameras by their spread. Pass explicit bounds otherwise.

    Parameters
    ----------
    views : sequence of objects with ``to_world`` (4, 4), ``fx, fy, cx, cy``
        and ``image`` (H, W, ...) or ``width, height``

    Returns
    -------
    (2, 3) float64
    """
    c, d = _camera_centres_dirs(views)
    # least squares: sum_i (I - d_i d_i^T) (x - c_i) = 0, regularized towards
    # the camera centroid for (near-)parallel axes
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    lam = 1e-3 * len(c)
    a = proj.sum(0) + lam * np.eye(3)
    b = np.einsum("kij,kj->i", proj, c) + lam * c.mean(0)
    centre = np.linalg.solve(a, b)
    if len(c) == 1 or np.linalg.cond(proj.sum(0)) > 1e6:
        spread = max(float(np.ptp(c, axis=0).max()), 1.0) if len(c) > 1 else 1.0
        centre = c.mean(0) + d.mean(0) * spread
    dist = np.linalg.norm(c - centre, axis=1)
    tans = []
    for view in views:
        w, h = _image_size(view)
        cx, cy = float(view.cx), float(view.cy)
        tans.append(min(min(cx, w - cx) / float(view.fx), min(cy, h - cy) / float(view.fy)))
    r = max(float(dist.min()) * min(tans), 1e-6)
    return np.stack([centre - r, centre + r])


def _carve(views, bounds, resolution, threshold, min_views, outside):
    b = _as_bounds(bounds)
    res = int(resolution)
    h = (b[1] - b[0]) / res
    axes = [b[0, a] + (np.arange(res) + 0.5) * h[a] for a in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    keep = np.ones(len(centres), bool)
    seen = np.zeros(len(centres), np.int64)
    for view in views:
        if getattr(view, "image", None) is None:
            raise ValueError("visual_hull_bounds needs every view's image (alpha mask)")
        img = np.asarray(view.image)
        alpha = img[..., 3] if img.ndim == 3 else img
        hgt, wid = alpha.shape[:2]
        uv, z = project_points(centres, view)
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        inside = (z > 0) & (col >= 0) & (col < wid) & (row >= 0) & (row < hgt)
        if outside == "carve":
            keep &= inside
        idx = np.flatnonzero(inside)
        fg = alpha[row[idx].astype(np.int64), col[idx].astype(np.int64)] > threshold
        keep[idx[~fg]] = False
        seen[idx] += 1
    keep &= seen >= min_views
    return centres[keep], h


def visual_hull_bounds(views, threshold: float = 0.05, resolution: int = 64,
                       initial_bounds=None, min_views: int | None = None, passes: int = 2,
                       outside: str = "keep"):
    """The box enclosing the visual hull of alpha masks.

    A voxel grid over ``initial_bounds`` is carved: a voxel is kept when its
    centre projects (see :func:`project_points`) onto a pixel with
    ``alpha > threshold`` in every view whose image it falls in, and falls
    in at least ``min_views`` images. Views it projects outside of (or
    behind) do not carve it (``outside='keep'``; ``'carve'`` removes it,
    right when every view sees the whole object). Later passes carve again at the same resolution
    over the previous pass's result, tightening the box.

    Parameters
    ----------
    views : sequence of objects
        Each with ``image`` (H, W, 4) (alpha in channel 3; an (H, W) array is
        taken as the alpha itself), ``to_world`` (4, 4) camera-to-world,
        ``fx, fy, cx, cy`` in pixels (and ``width, height``, unused: the
        image's shape is authoritative).
    threshold : float
        Alpha above which a pixel is foreground.
    resolution : int
        Voxels per axis.
    initial_bounds : (2, 3) float, optional
        Region to carve; default :func:`initial_bounds_from_cameras`.
    min_views : int, optional
        Views a voxel must be seen in to be kept; default ``min(2,
        len(views))``. (A voxel seen by a single view is constrained only by
        that view's silhouette cone: behind or beside the other cameras, such
        voxels would otherwise survive far from the object.)
    passes : int
        Carving passes (>= 1).
    outside : {'keep', 'carve'}
        What a view does to voxels outside its image or behind it.

    Returns
    -------
    (2, 3) float64
        Bounds of the kept voxels (their full extent) padded by one voxel.

    Raises
    ------
    ValueError
        No voxel survives (masks empty, or cameras not looking at the box).
    """
    views = list(views)
    if not views:
        raise ValueError("visual_hull_bounds needs at least one view")
    if min_views is None:
        min_views = min(2, len(views))
    if outside not in ("keep", "carve"):
        raise ValueError(f"outside must be 'keep' or 'carve', got {outside!r}")
    b = initial_bounds_from_cameras(views) if initial_bounds is None else _as_bounds(initial_bounds)
    for _ in range(max(1, int(passes))):
        kept, h = _carve(views, b, resolution, threshold, min_views, outside)
        if len(kept) == 0:
            raise ValueError("no voxel of the visual hull survives: empty masks, or the "
                             "cameras do not see the initial bounds")
        b = np.stack([kept.min(0) - 1.5 * h, kept.max(0) + 1.5 * h])
    return b
