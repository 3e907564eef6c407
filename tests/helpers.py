"""Helpers shared by the test suite: paths, the Mitsuba variant, scenes of
``tetmesh`` shapes and rays.

Import as ``from tests.helpers import make_scene, rays_at`` (``tests`` is a
package; pytest puts the repository root on ``sys.path``). The float64
reference renderer is :mod:`tests.reference`.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

#: The repository root and the shared data sets next to it.
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
#: A shared data set that is absent fails the test that needs it instead of skipping it
#: (``MI_TETVR_REQUIRE_DATA=1``, which ``.ci/run`` sets: CI has the data, and a lost copy
#: must not pass unseen).
REQUIRE_DATA = os.environ.get("MI_TETVR_REQUIRE_DATA", "") not in ("", "0")
#: The bundled scenes as ``mi-tetvr make-scenes`` writes them in the checkout.
SCENES = ROOT / "scenes"

#: The Mitsuba variant of the test suite (``MI_TETVR_VARIANT``, default ``llvm_ad_rgb``).
VARIANT = os.environ.get("MI_TETVR_VARIANT", "") or "llvm_ad_rgb"


def shared_data(*parts):
    """The path ``../shared/data/PARTS`` (a file or a folder). A test that needs it is
    skipped where it is absent, and fails under :data:`REQUIRE_DATA`."""
    import pytest
    path = DATA.joinpath(*parts)
    if not path.exists():
        if REQUIRE_DATA:
            pytest.fail(f"{path} is absent, and MI_TETVR_REQUIRE_DATA is set (CI runs with the "
                        f"shared data)")
        pytest.skip(f"{path} is absent")
    return path


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


def tetproj_scene(V, T, scalar, transfer_function="gray", value_range=(-1.0, 1.0),
                  **integrator):
    """A scene of one scalar mesh (its transfer function over ``value_range``;
    ``None``: the scalar's range) under ``tetproj`` with these properties."""
    import mitsuba as mi
    import mi_tetvr
    rng = {} if value_range is None else {"value_min": value_range[0],
                                          "value_max": value_range[1]}
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetproj", **integrator},
                         "m": mi_tetvr.tetmesh_dict(V, T, scalar=scalar,
                                                    transfer_function=transfer_function,
                                                    **rng)})


def project_rays(scene, origins, directions):
    """``tetproj``'s ``project`` of rays, no gradients: ``(color (3, k), met (k,),
    value)`` as numpy (float64, bool, float64: the scalar (k,) or the point (3, k))."""
    import drjit as dr
    with dr.suspend_grad():
        color, met, value = scene.integrator().project(scene, make_rays(origins, directions))
    return (np.array(color, np.float64).reshape(3, -1), np.array(met, bool),
            np.array(value, np.float64))


def seeded_sampler(k, seed=0):
    """An ``independent`` sampler seeded for ``k`` rays (the same numbers
    for the same seed)."""
    import mitsuba as mi
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, k)
    return sampler


def make_rays(origins, directions):
    """``mi.Ray3f`` of (k, 3) origins and directions (normalized here)."""
    import mitsuba as mi
    o = np.asarray(origins, np.float32)
    d = np.asarray(directions, np.float64)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    # (in memory of Dr.Jit's own: see mi_tetvr.render.buffers.owned)
    from mi_tetvr.render.buffers import owned
    o, d = ([owned(mi.Float, np.ascontiguousarray(c)) for c in a.T] for a in (o, d))
    return mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d))


def render_rays(scene, origins, directions, sampler=None):
    """Run tetvr.sample() on explicit rays; returns rgb (k, 3), alpha (k,)."""
    import drjit as dr
    ray = make_rays(origins, directions)
    L, _, aovs, _ = scene.integrator().sample(dr.ADMode.Primal, scene, sampler, ray,
                                              None, None, True)
    return np.array(L).reshape(3, -1).T.astype(np.float64), np.array(aovs[0], np.float64)


def rays_at(rng, k, radius=4.0, target_extent=0.8):
    """Rays from a sphere of ``radius`` towards random points of a box."""
    o = rng.normal(size=(k, 3))
    o *= radius / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-target_extent, target_extent, (k, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


class Problem:
    """A scene and fixed rays; the objective is sum(wL . rgb + wa * alpha) of
    ``tetvr.sample()``, its gradient (backward mode), its derivative along
    given directions (forward mode) and central differences.

    ``mesh`` is ``(V, T, color, opacity)`` for :func:`make_scene`, or
    ``scene`` a loaded scene; ``keys`` the parameters differentiated (Float
    or Color3f parameters); ``sampled``: every pass gets a sampler seeded
    alike (scenes with surfaces).
    """

    def __init__(self, mesh, o, d, rng, scene=None,
                 keys=("mesh0.vertex_color", "mesh0.vertex_opacity",
                       "mesh0.vertex_positions"), sampled=False):
        import mitsuba as mi
        self.mesh, self.keys = mesh, tuple(keys)
        self.scene = make_scene(mesh) if scene is None else scene
        self.params = mi.traverse(self.scene)
        self.integrator = self.scene.integrator()
        self.ray = make_rays(o, d)
        self.sampled = sampled
        self.wL = rng.normal(size=(len(o), 3))
        self.wa = rng.normal(size=len(o))

    def sample(self, mode, **kw):
        import drjit as dr
        sampler = seeded_sampler(dr.width(self.ray)) if self.sampled else None
        return self.integrator.sample(mode, self.scene, sampler, self.ray, active=True, **kw)

    def objective(self):
        import drjit as dr
        with dr.suspend_grad():
            L, _, aovs, _ = self.sample(dr.ADMode.Primal, δL=None, state_in=None)
        return (np.array(L, np.float64).T * self.wL).sum() + (np.array(aovs[0]) * self.wa).sum()

    def backward(self):
        import drjit as dr
        import mitsuba as mi
        for k in self.keys:
            dr.enable_grad(self.params[k])
            dr.set_grad(self.params[k], 0)
        with dr.suspend_grad():
            _, _, _, state = self.sample(dr.ADMode.Primal, δL=None, state_in=None)
            self.sample(dr.ADMode.Backward, δL=mi.Color3f(*self.wL.T), state_in=state,
                        δaovs=[mi.Float(self.wa)])
        grads = {k: np.array(dr.grad(self.params[k]), np.float64).ravel() for k in self.keys}
        self.disable()
        return grads

    def forward(self, directions):
        """Forward mode along ``directions`` (key -> array) at once. Every key
        of the problem is differentiated (those without a direction carry
        evaluated zeros), so that every call runs the same kernel."""
        import drjit as dr
        for k in self.keys:
            v = directions.get(k)
            if v is None:
                v = np.zeros(np.array(self.params[k]).size)
            dr.enable_grad(self.params[k])
            dr.set_grad(self.params[k], self._typed(k, v))
        with dr.suspend_grad():
            _, _, _, state = self.sample(dr.ADMode.Primal, δL=None, state_in=None)
            δL, _, δaovs, _ = self.sample(dr.ADMode.Forward, δL=None, state_in=state)
        self.disable()
        return ((np.array(δL, np.float64).T * self.wL).sum()
                + (np.array(δaovs[0], np.float64) * self.wa).sum())

    def disable(self):
        import drjit as dr
        for k in self.keys:
            dr.disable_grad(self.params[k])

    def central(self, key, direction, h):
        """Central difference of the objective along ``direction``."""
        base = np.array(self.params[key], np.float64).ravel()
        vals = []
        for sign in (1, -1):
            self.params[key] = self._typed(key, base + sign * h * np.asarray(direction))
            self.params.update()
            vals.append(self.objective())
        self.params[key] = self._typed(key, base)
        self.params.update()
        return (vals[0] - vals[1]) / (2 * h)

    def _typed(self, key, values):
        """Flat ``values`` as the type of parameter ``key`` (Float, or one Color3f)."""
        import mitsuba as mi
        cls = type(self.params[key])
        values = np.asarray(values, np.float64)
        return mi.Float(values) if cls is mi.Float else cls(*values.tolist())

    def finite_difference(self, key, index, h):
        """Central difference w.r.t. one entry of a parameter."""
        e = np.zeros(np.array(self.params[key]).size)
        e[index] = 1.0
        return self.central(key, e, h)


def interior_positions(V, T):
    """(3 n,) mask of the position entries of vertices off the boundary
    (moving a boundary vertex moves a silhouette, which has no derivative
    term)."""
    from mi_tetvr.mesh.topology import build_topology
    inner = np.ones(len(V), bool)
    inner[np.unique(build_topology(V, T, warn=False).boundary_faces)] = False
    return np.repeat(inner, 3)


def check_along(problem, key, h, rng, restrict=None):
    """A :class:`Problem`'s gradient w.r.t. ``key`` along a random direction
    (``restrict(direction)`` keeps the entries where the objective is
    smooth): reverse mode against central differences with step ``h`` (5 %),
    forward against reverse (1 %)."""
    g = problem.backward()[key]
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0
    direction = rng.normal(size=len(g))
    if restrict is not None:
        direction = restrict(direction)
    reverse = float(direction @ g)
    fd = problem.central(key, direction, h)
    assert abs(reverse - fd) < 0.05 * abs(fd), (reverse, fd)
    fwd = problem.forward({key: direction})
    assert abs(fwd - reverse) < 0.01 * abs(reverse), (fwd, reverse)


def vtk_plane(origin, normal):
    """VTK's implicit plane through ``origin`` with ``normal`` (the clip and
    cut filters' function)."""
    from vtkmodules.vtkCommonDataModel import vtkPlane
    plane = vtkPlane()
    plane.SetOrigin(*origin)
    plane.SetNormal(*normal)
    return plane


def vtk_tet_grid(V, T, **point_data):
    """A pyvista unstructured grid of the tets with float64 point arrays (the
    input of the VTK filters the tests compare with)."""
    import pyvista as pv
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: np.asarray(T)}, np.asarray(V, np.float64))
    for k, a in point_data.items():
        grid.point_data[k] = np.asarray(a, np.float64)
    return grid


def _render_at(params, key, base, x, scene):
    import mitsuba as mi
    params[key] = type(params[key])(x.astype(np.float32))
    params.update()
    img = np.array(mi.render(scene, spp=1), np.float64)
    params[key] = type(params[key])(base.astype(np.float32))
    params.update()
    return img


def check_derivatives(scene, checks):
    """The image's derivatives w.r.t. each parameter of ``checks`` (key ->
    ``(direction, h, smooth_share)``): forward mode along ``direction``
    against central differences with step ``h`` (5 % on the smooth pixels,
    which must be at least ``smooth_share`` of the pixels whose value moves),
    and reverse mode of a weighted sum of the image against forward mode
    (1e-4). A key is a scene parameter, or ``integrator.<name>`` one of the
    integrator's.

    All the keys are differentiated at once (each forward pass carries a
    tangent in one of them, zero in the others), so that a scene compiles one
    forward and one reverse kernel however many parameters it checks."""
    import drjit as dr
    import mitsuba as mi
    params = mi.traverse(scene)
    base = {k: np.array(params[k], np.float64) for k in checks}
    kind = {k: type(params[k]) for k in checks}

    def tangents(key):
        # (evaluated zeros, not literals: the same kernel for every key)
        for k in checks:
            v = np.asarray(checks[k][0], np.float64) if k == key else np.zeros(len(base[k]))
            dr.set_grad(params[k], kind[k](v.astype(np.float32)))

    def attach(on):
        for k in checks:
            dr.set_grad_enabled(params[k], on)

    attach(True)
    ad = {}
    for key in checks:
        tangents(key)
        ad[key] = np.array(dr.forward_to(mi.render(scene, params, spp=1)), np.float64)
    attach(False)
    w = np.random.default_rng(3).normal(size=next(iter(ad.values())).shape)
    attach(True)
    dr.backward(dr.sum(mi.render(scene, params, spp=1) * mi.TensorXf(w.astype(np.float32)),
                       axis=None))
    grads = {k: np.array(dr.grad(params[k]), np.float64) for k in checks}
    attach(False)
    for key, (direction, h, smooth_share) in checks.items():
        direction = np.asarray(direction, np.float64)
        f = {s: _render_at(params, key, base[key], base[key] + s * h * direction, scene)
             for s in (-1.0, -0.5, 0.0, 0.5, 1.0)}
        fd = [(f[1.0] - f[-1.0]) / (2 * h), (f[0.5] - f[-0.5]) / h]
        one_sided = [(f[0.5] - f[0.0]) / (h / 2), (f[0.0] - f[-0.5]) / (h / 2)]
        scale = np.abs(fd[1]).max()
        assert scale > 0, key
        moving = np.abs(fd[1]) > 1e-3 * scale
        # Smooth: no kink or jump within h (the differences at both steps and
        # on both sides agree).
        smooth = (moving & (np.abs(fd[0] - fd[1]) <= 0.01 * np.abs(fd[1]))
                  & (np.abs(one_sided[0] - one_sided[1]) <= 0.05 * np.abs(fd[1])))
        assert smooth.sum() >= smooth_share * moving.sum() and smooth.sum() > 50, \
            (key, smooth.sum(), moving.sum())
        err = np.abs(ad[key] - fd[1])[smooth] / np.abs(fd[1])[smooth]
        assert err.max() < 0.05, (key, err.max(), np.median(err))
        reverse, forward = grads[key] @ direction, float(np.sum(w * ad[key]))
        assert abs(reverse - forward) <= 1e-4 * np.abs(w * ad[key]).sum(), \
            (key, reverse, forward)


def grid_field():
    """``(V, T, scalar)``: a jittered 4x4x4 grid of [-1, 1]^3 and a smooth
    scalar that spans [-1, 1] several times across it."""
    from mi_tetvr.mesh.generate import grid_mesh
    V, T = grid_mesh(4, jitter=0.12, seed=7)
    return V, T, np.sin(2.2 * V[:, 0] + 1.3 * V[:, 1]) * np.cos(1.7 * V[:, 2])


def grid_field_scene(integrator, transfer_function, size, resolution=64):
    """A scene of :func:`grid_field` (shape ``m``, the scalar over [-1, 1]
    through ``resolution`` texels) seen by an orthographic camera on
    ``size`` x ``size`` pixels, one ray each, rendered by ``integrator``."""
    import mitsuba as mi
    import mi_tetvr
    V, T, scalar = grid_field()
    return mi.load_dict({
        "type": "scene",
        "integrator": integrator,
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=[2.5, 1.5, 3.0], target=[0, 0, 0], up=[0, 1, 0])
                   @ mi.ScalarTransform4f().scale([1.6, 1.6, 1]),
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "pixel_format": "rgb", "rfilter": {"type": "box"}}},
        "m": mi_tetvr.tetmesh_dict(V, T, scalar=scalar, transfer_function=transfer_function,
                                   value_min=-1.0, value_max=1.0, tf_resolution=resolution)})


def start_browser(width=900, height=700):
    """Selenium's Chrome on Debian's headless Chromium (software WebGL), or a
    skip that says what is missing."""
    import pytest
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (pip install -e '.[test]' installs it)")
    driver = shutil.which("chromedriver")
    if shutil.which("chromium") is None or driver is None:
        pytest.skip("no Chromium here: setup.sh installs Debian's chromium and "
                    "chromium-driver; where apt cannot install them the browser test "
                    "cannot run")
    options = webdriver.ChromeOptions()
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
              "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
              f"--window-size={width},{height}"):
        options.add_argument(a)
    return webdriver.Chrome(service=Service(driver), options=options)
