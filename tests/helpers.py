"""Helpers shared by the test suite: paths, the Mitsuba variant, scenes of
``tetmesh`` shapes and rays.

Import as ``from tests.helpers import make_scene, rays_at`` (``tests`` is a
package; pytest puts the repository root on ``sys.path``). The float64
reference renderer is :mod:`tests.reference`.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

#: The repository root and the shared data sets next to it.
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

#: The Mitsuba variant of the test suite (``MI_TETVR_VARIANT``, default ``llvm_ad_rgb``).
VARIANT = os.environ.get("MI_TETVR_VARIANT", "") or "llvm_ad_rgb"


def use_variant(name=VARIANT):
    """Set the Mitsuba variant ``name`` and register the mi_tetvr plugins with it.

    Raises
    ------
    RuntimeError
        If the variant is not an autodiff RGB variant of this Mitsuba build, or
        its Dr.Jit backend (LLVM or CUDA) cannot run on this machine.
    """
    import drjit as dr
    import mitsuba as mi

    if name not in mi.variants() or "_ad_" not in name or not name.endswith("_rgb"):
        ad_rgb = [v for v in mi.variants() if "_ad_" in v and v.endswith("_rgb")]
        raise RuntimeError(f"MI_TETVR_VARIANT={name!r}: not an autodiff RGB variant of this "
                           f"Mitsuba build (available: {', '.join(ad_rgb)})")
    backend = {"llvm": dr.JitBackend.LLVM, "cuda": dr.JitBackend.CUDA}[name.split("_")[0]]
    if not dr.has_backend(backend):
        need = "a CUDA GPU and driver" if backend == dr.JitBackend.CUDA else "libLLVM"
        raise RuntimeError(f"MI_TETVR_VARIANT={name!r}: Dr.Jit's {backend.name} backend is not "
                           f"available on this machine (it needs {need})")
    if mi.variant() != name:
        mi.set_variant(name)
    import mi_tetvr
    mi_tetvr.register()
    return name


def make_scene(*meshes, background=None, **integrator):
    """A scene of tetmesh shapes given as (vertices, tets, color, opacity)."""
    import mitsuba as mi
    import mi_tetvr
    d = {"type": "scene", "integrator": {"type": "tetvr", **integrator}}
    for i, m in enumerate(meshes):
        d[f"mesh{i}"] = mi_tetvr.tetmesh_dict(*m)
    if background is not None:
        d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": background}}
    return mi.load_dict(d)


def render_rays(scene, origins, directions):
    """Run tetvr.sample() on explicit rays; returns rgb (k, 3), alpha (k,)."""
    import drjit as dr
    import mitsuba as mi
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
