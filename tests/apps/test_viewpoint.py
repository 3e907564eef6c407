"""The best-viewpoint search (``mi_tetvr.apps.viewpoint``): the opacity
entropy against its formula, its forward-mode derivative against finite
differences, the ascent against the best of sampled views, and the
``viewpoint`` command's outputs."""
import json
import subprocess
import sys

import numpy as np
import pytest

import mitsuba as mi
import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.apps.viewpoint import (ViewpointSearch, best_viewpoint, default_starts,
                                     opacity_entropy)
from mi_tetvr.camera import fibonacci_sphere
from tests.helpers import ROOT, VARIANT


@pytest.fixture(scope="module")
def slab():
    """A flat slab of fog (thin along z): it spreads its opacity over the
    image best when seen along z."""
    V, T = grid_mesh((8, 4, 2), jitter=0.05, seed=1)
    V = V * np.array([1.0, 0.6, 0.25])
    S = 2.0 * np.exp(-2 * ((V / [1, 0.6, 0.25]) ** 2).sum(1))
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr"},
        "sensor": {"type": "perspective", "fov": 40,
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                   "film": {"type": "hdrfilm", "width": 32, "height": 32,
                            "rfilter": {"type": "box"}}},
        "mesh0": mi_tetvr.tetmesh_dict(V, T, np.full((len(V), 3), 0.7), S)})
    return ViewpointSearch(scene, (0, 0, 0), 3.5)


def test_opacity_entropy_formula():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, 500)
    a[:100] = 0
    p = a / a.sum()
    ref = -(p[p > 0] * np.log(p[p > 0])).sum() / np.log(len(a))
    assert abs(float(opacity_entropy(mi.Float(a)).array[0]) - ref) < 1e-5
    assert abs(float(opacity_entropy(mi.Float(np.ones(64))).array[0]) - 1.0) < 1e-6
    lon, lat = fibonacci_sphere(256)
    z = np.sin(np.radians(lat))
    assert abs(z.mean()) < 1e-3 and np.all(np.abs(lat) < 90)


def test_entropy_gradient_against_finite_differences(slab):
    """Forward-mode derivatives w.r.t. longitude and latitude (per degree)
    against central differences of 1 degree (5 %)."""
    lon, lat = 60.0, 30.0
    h, glon, glat = slab.gradient(lon, lat)
    assert abs(h - slab.entropy(lon, lat)) < 1e-6
    fd_lon = (slab.entropy(lon + 1, lat) - slab.entropy(lon - 1, lat)) / 2
    fd_lat = (slab.entropy(lon, lat + 1) - slab.entropy(lon, lat - 1)) / 2
    assert abs(glat) > 1e-3
    assert abs(glon - fd_lon) < 0.05 * max(abs(fd_lon), abs(fd_lat))
    assert abs(glat - fd_lat) < 0.05 * abs(fd_lat)


def test_ascent_matches_the_best_sampled_view(slab):
    """Four starts of ten steps reach the entropy of the best of 64 sampled
    views (measured: 100.1 %), looking along the slab's thin axis."""
    r = best_viewpoint(slab, default_starts(4), iterations=10, samples=64)
    assert r["ratio_to_best_sampled"] >= 0.99, r["ratio_to_best_sampled"]
    assert abs(r["latitude"]) > 60
    # every climb goes up from its start at latitude 45 (the slab seen obliquely)
    for path in r["paths"]:
        assert path[-1][2] > path[0][2] + 0.01, (path[0], path[-1])
    # the reported entropy is the chosen view's, recomputed from its rendered alpha with
    # the formula (numpy, float64)
    a = slab.image(r["longitude"], r["latitude"])[..., 3].astype(np.float64).ravel()
    p = a / a.sum()
    h = -(p[p > 0] * np.log(p[p > 0])).sum() / np.log(len(a))
    assert abs(h - r["entropy"]) < 1e-5, (h, r["entropy"])


def test_viewpoint_command(tmp_path, data_dir):
    out = tmp_path / "vp"
    r = subprocess.run([sys.executable, "-m", "mi_tetvr.cli", "viewpoint",
                        str(data_dir / "tets" / "spx" / "spx.vtk"), "--out", str(out),
                        "--tf", str(ROOT / "scenes" / "tf_radial.json"), "--res", "24",
                        "--samples", "16", "--starts", "2", "--iterations", "3", "--quiet",
                        "--variant", VARIANT], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    result = json.loads((out / "viewpoint.json").read_text())
    for k in ("longitude", "latitude", "entropy", "best_sampled", "paths", "samples"):
        assert k in result
    assert len(result["samples"]["entropy"]) == 16 and len(result["paths"]) == 2
    for name in ("view.png", "viewpoint.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "opacity entropy" in r.stdout
