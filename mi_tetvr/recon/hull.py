"""The region to reconstruct, from cameras and alpha masks.

Free functions over :class:`~mi_tetvr.camera.Camera` s and
:class:`~mi_tetvr.recon.datasets.View` s (camera convention: :mod:`mi_tetvr.camera`),
numpy and scipy only. They give the mesh initializers of :mod:`mi_tetvr.mesh.initial` their box.

* :func:`frusta_bounds` -- the box of what every camera sees (the intersection of the viewing
  pyramids), from the cameras alone; :meth:`mi_tetvr.recon.datasets.Dataset.bounds` falls back
  to it when a data set has neither a box nor sparse points.
* :func:`visual_hull_bounds` -- the box enclosing the visual hull of alpha masks, carved on a
  voxel grid inside :func:`frusta_bounds` (or a given box).
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from mi_tetvr.extras import needs
from mi_tetvr.mesh.topology import check_bounds

__all__ = ["frusta_bounds", "visual_hull_bounds"]


def frusta_bounds(cameras: Sequence, far: Optional[float] = None) -> np.ndarray:
    """The bounding box of the region every camera sees.

    The intersection of all cameras' viewing pyramids is a convex polytope; its bounding box is
    found by linear programming (one program per face of the box). For inward-looking captures
    (NeRF-synthetic) the intersection is bounded; when it is not (forward-facing captures),
    depth along each camera axis is capped at ``far``. An empty intersection falls back to the
    box of the camera centers.

    Parameters
    ----------
    cameras : sequence of Camera
    far : float, optional
        Depth cap for unbounded intersections; default twice the spread of the camera
        centers, at least 1.

    Returns
    -------
    (2, 3) float64
        ``[min, max]``.
    """
    with needs("recon", "the cameras' common bounds"):
        from scipy.optimize import linprog
    cameras = list(cameras)
    if not cameras:
        raise ValueError("frusta_bounds needs at least one camera")
    centers = np.array([c.center for c in cameras])
    spread = float(np.linalg.norm(centers.max(0) - centers.min(0)))
    rows, rhs = [], []
    for cam in cameras:
        r, c = cam.to_world[:3, :3], cam.to_world[:3, 3]
        if cam.is_orthographic:
            # a slab: s (cx - w) <= q_x <= s cx, s (cy - h) <= q_y <= s cy, q_z >= 0
            s = cam.pixel_size
            for axis, hi, lo in ((0, s * cam.cx, s * (cam.cx - cam.width)),
                                 (1, s * cam.cy, s * (cam.cy - cam.height))):
                rows += [r[:, axis], -r[:, axis]]
                rhs += [r[:, axis] @ c + hi, -(r[:, axis] @ c + lo)]
            rows.append(-r[:, 2])
            rhs.append(-r[:, 2] @ c)
            continue
        # Camera frame q = R^T (p - c); each constraint a . q >= 0 (inside the pyramid).
        for a in ([-cam.fx, 0, cam.cx], [cam.fx, 0, cam.width - cam.cx],
                  [0, -cam.fy, cam.cy], [0, cam.fy, cam.height - cam.cy]):
            n = r @ np.asarray(a, np.float64)           # world normal: n . (p - c) >= 0
            rows.append(-n)
            rhs.append(-n @ c)

    def solve(a_ub, b_ub):
        out = np.empty((2, 3))
        for k in range(3):
            for s, sign in ((0, 1.0), (1, -1.0)):
                cost = np.zeros(3)
                cost[k] = sign
                res = linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=[(None, None)] * 3,
                              method="highs")
                if res.status != 0:
                    return res.status
                out[s, k] = res.x[k]
        return out

    a_ub, b_ub = np.array(rows), np.array(rhs)
    out = solve(a_ub, b_ub)
    if isinstance(out, int) and out == 3:                 # unbounded: cap the depth
        far = max(2.0 * spread, 1.0) if far is None else float(far)
        caps = [cam.to_world[:3, 2] for cam in cameras]  # z . (p - c) <= far
        a_ub = np.vstack([a_ub, caps])
        b_ub = np.concatenate([b_ub, [z @ cam.center + far for z, cam in zip(caps, cameras)]])
        out = solve(a_ub, b_ub)
    if isinstance(out, int):                              # infeasible: no common region
        return np.stack([centers.min(0), centers.max(0)])
    return out


def _carve(views, bounds, resolution, threshold, min_views, outside):
    b = check_bounds(bounds)
    res = int(resolution)
    h = (b[1] - b[0]) / res
    axes = [b[0, a] + (np.arange(res) + 0.5) * h[a] for a in range(3)]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    keep = np.ones(len(centers), bool)
    seen = np.zeros(len(centers), np.int64)
    for view in views:
        if view.image is None:
            raise ValueError("visual_hull_bounds needs every view's image (alpha mask)")
        img = np.asarray(view.image)
        alpha = img[..., 3] if img.ndim == 3 else img
        hgt, wid = alpha.shape[:2]
        uv, z = view.camera.project(centers)
        col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        inside = (z > 0) & (col >= 0) & (col < wid) & (row >= 0) & (row < hgt)
        if outside == "carve":
            keep &= inside
        idx = np.flatnonzero(inside)
        fg = alpha[row[idx].astype(np.int64), col[idx].astype(np.int64)] > threshold
        keep[idx[~fg]] = False
        seen[idx] += 1
    keep &= seen >= min_views
    return centers[keep], h


def visual_hull_bounds(views, threshold: float = 0.05, resolution: int = 64,
                       initial_bounds=None, min_views: int | None = None, passes: int = 2,
                       outside: str = "keep") -> np.ndarray:
    """The box enclosing the visual hull of alpha masks.

    A voxel grid over ``initial_bounds`` is carved: a voxel is kept when its center projects
    (:meth:`Camera.project <mi_tetvr.camera.Camera.project>`) onto a pixel with
    ``alpha > threshold`` in every view whose image it falls in, and falls in at least
    ``min_views`` images. Views it projects outside of (or behind) do not carve it
    (``outside='keep'``; ``'carve'`` removes it, right when every view sees the whole object).
    Later passes carve again at the same resolution over the previous pass's result,
    tightening the box.

    Parameters
    ----------
    views : sequence of View
        Each with its ``camera`` and its ``image`` (H, W, 4) (alpha in channel 3; an (H, W)
        array is taken as the alpha itself; the image's shape is authoritative).
    threshold : float
        Alpha above which a pixel is foreground.
    resolution : int
        Voxels per axis.
    initial_bounds : (2, 3) float, optional
        Region to carve; default :func:`frusta_bounds` of the views' cameras (the region every
        view sees).
    min_views : int, optional
        Views a voxel must be seen in to be kept; default ``min(2, len(views))``. (A voxel seen
        by a single view is constrained only by that view's silhouette cone: behind or beside
        the other cameras, such voxels would otherwise survive far from the object.)
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
    b = (frusta_bounds([v.camera for v in views]) if initial_bounds is None
         else check_bounds(initial_bounds))
    for _ in range(max(1, int(passes))):
        kept, h = _carve(views, b, resolution, threshold, min_views, outside)
        if len(kept) == 0:
            raise ValueError("no voxel of the visual hull survives: empty masks, or the "
                             "cameras do not see the initial bounds")
        b = np.stack([kept.min(0) - 1.5 * h, kept.max(0) + 1.5 * h])
    return b
