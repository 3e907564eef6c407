import sys
from pathlib import Path

import numpy as np
import pytest

import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import drjit as dr  # noqa: E402
import mi_tetvr  # noqa: E402,F401

sys.path.insert(0, str(Path(__file__).parent))

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def data_dir():
    if not DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return DATA


def make_scene(*meshes, background=None, **integrator):
    """A scene of tetmesh shapes given as (vertices, tets, color, opacity)."""
    d = {"type": "scene", "integrator": {"type": "tetvr", **integrator}}
    for i, m in enumerate(meshes):
        d[f"mesh{i}"] = mi_tetvr.tetmesh_dict(*m)
    if background is not None:
        d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": background}}
    return mi.load_dict(d)


def render_rays(scene, origins, directions):
    """Run tetvr.sample() on explicit rays; returns rgb (k, 3), alpha (k,)."""
    o = np.asarray(origins, np.float32)
    d = np.asarray(directions, np.float64)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*d.T))
    L, _, aovs, _ = scene.integrator().sample(dr.ADMode.Primal, scene, None, ray,
                                              None, None, True)
    return np.array(L).reshape(3, -1).T.astype(np.float64), np.array(aovs[0], np.float64)


def rays_at(rng, k, radius=4.0, target_extent=0.8):
    """Rays from a sphere of ``radius`` towards random points of a box."""
    o = rng.normal(size=(k, 3))
    o *= radius / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-target_extent, target_extent, (k, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)
