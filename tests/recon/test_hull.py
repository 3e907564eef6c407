"""The region to reconstruct: frusta bounds and the visual hull of alpha masks."""
import math

import numpy as np
import pytest

from mi_tetvr.camera import Camera
from mi_tetvr.recon.datasets import Dataset, View
from mi_tetvr.recon.hull import frusta_bounds, visual_hull_bounds
from tests.test_camera import box_mask, mi_look_at, sphere_mask


def test_frusta_bounds():
    cams = [Camera.look_at(4 * np.array([math.cos(t), math.sin(t), 0.3]), [0, 0, 0], [0, 0, 1],
                           20, 20, fov_x=40.0)
            for t in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    lo, hi = frusta_bounds(cams)
    assert np.all(lo < 0) and np.all(hi > 0)
    assert np.all(hi - lo < 4)
    for c in cams:                                   # every camera sees the whole box
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        uv, depth = c.project(corners)
        assert np.all(depth > 0)
    # a data set without box or points falls back to them
    views = [View(f"v{i}", c) for i, c in enumerate(cams)]
    np.testing.assert_array_equal(Dataset(train=views).bounds(), np.stack([lo, hi]))
    # forward-facing cameras: unbounded intersection, capped at `far`
    fwd = [Camera.look_at([0.1 * i, 0, 0], [0.1 * i, 0, 1], [0, 1, 0], 20, 20, fov_x=40.0)
           for i in range(3)]
    lo, hi = frusta_bounds(fwd, far=5.0)
    assert hi[2] == pytest.approx(5.0, rel=1e-6) and lo[2] > 0
    lo, hi = Dataset(train=[View(f"f{i}", c) for i, c in enumerate(fwd)]).bounds(far=5.0)
    assert hi[2] == pytest.approx(5.0, rel=1e-6) and lo[2] > 0
    # cameras that see no common region: the box of their centers
    apart = [Camera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], 20, 20, fov_x=40.0),
             Camera.look_at([1, 1, 1], [1, 1, 0], [0, 1, 0], 20, 20, fov_x=40.0)]
    np.testing.assert_allclose(frusta_bounds(apart), [[0, 0, 0], [1, 1, 1]])


def _six_views(mask_fn, W=40, H=32, dist=4.0):
    f = W / 2 / np.tan(np.radians(40.0) / 2)
    dirs = [([1, 0, 0], [0, 1, 0]), ([-1, 0, 0], [0, 1, 0]), ([0, 1, 0], [0, 0, 1]),
            ([0, -1, 0], [0, 0, 1]), ([0, 0, 1], [0, 1, 0]), ([0, 0, -1], [0, 1, 0])]
    views = []
    for dvec, up in dirs:
        c2w = mi_look_at((dist * np.asarray(dvec, float)).tolist(), [0.0, 0.0, 0.0], up)
        cam = Camera(W, H, f, f, W / 2, H / 2, c2w)
        alpha = mask_fn(cam, W, H).astype(np.float64)
        views.append(View("v", cam, np.concatenate([np.zeros((H, W, 3)), alpha[..., None]], -1)))
    return views


def test_visual_hull_bounds_sphere_and_box():
    center, radius = np.array([0.2, -0.1, 0.15]), 0.5
    views = _six_views(lambda c, W, H: sphere_mask(c, W, H, center, radius))
    b = visual_hull_bounds(views, resolution=32)
    lo, hi = center - radius, center + radius
    assert np.all(b[0] <= lo) and np.all(b[1] >= hi)
    assert np.all(b[1] - b[0] < 1.4 * 2 * radius), b
    # an explicit initial box larger than what the views see: voxels outside
    # the images must be carved for a tight box (every view sees the object)
    lo, hi = np.array([-0.3, -0.6, -0.2]), np.array([0.5, 0.2, 0.4])
    views = _six_views(lambda c, W, H: box_mask(c, W, H, lo, hi))
    b = visual_hull_bounds(views, resolution=32, initial_bounds=[[-2, -2, -2], [2, 2, 2]],
                           outside="carve")
    assert np.all(b[0] <= lo) and np.all(b[1] >= hi)
    assert np.all((b[1] - b[0]) < (hi - lo) + 0.4), b
    # empty masks: nothing survives
    for v in views:
        v.image[..., 3] = 0
    with pytest.raises(ValueError):
        visual_hull_bounds(views, resolution=8)
    # every view needs its image
    with pytest.raises(ValueError, match="image"):
        visual_hull_bounds([View("v", v.camera) for v in views], resolution=8)
