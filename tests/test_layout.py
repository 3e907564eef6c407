"""The package layout: every exported name resolves, and the numpy
sub-packages import and run without a Mitsuba variant."""
import importlib
import subprocess
import sys

import pytest

from tests.helpers import ROOT

PACKAGES = ["mi_tetvr", "mi_tetvr.mesh", "mi_tetvr.render", "mi_tetvr.grid", "mi_tetvr.recon",
            "mi_tetvr.apps"]

#: The layers, lowest first: a module imports only from its own layer and those below.
LAYERS = [("mi_tetvr.color", "mi_tetvr.transfer", "mi_tetvr.camera", "mi_tetvr.progress",
           "mi_tetvr._lazy"),
          ("mi_tetvr.mesh",), ("mi_tetvr.render",), ("mi_tetvr.grid",), ("mi_tetvr.recon",),
          ("mi_tetvr.apps",), ("mi_tetvr.cli",)]


def _layer(module):
    for rank, names in enumerate(LAYERS):
        if any(module == n or module.startswith(n + ".") for n in names):
            return rank
    return None


def test_no_module_imports_a_layer_above_its_own():
    """Every import of mi_tetvr's modules (also those inside functions) reaches its own
    layer or one below: the numpy utilities, mesh, render, grid, recon, apps, cli."""
    import ast
    bad = []
    for path in sorted((ROOT / "mi_tetvr").rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(
            ".__init__")
        rank = _layer(module)
        if rank is None:             # the package's own __init__ (registration, exports)
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                other = _layer(name)
                if other is not None and other > rank:
                    bad.append(f"{module} imports {name}")
    assert not bad, bad


@pytest.mark.parametrize("name", PACKAGES)
def test_exports_resolve(name):
    mod = importlib.import_module(name)
    assert len(mod.__all__) == len(set(mod.__all__)), "a name exported twice"
    missing = [n for n in mod.__all__ if getattr(mod, n, None) is None]
    assert not missing, f"{name}.__all__ names that do not resolve: {missing}"


def test_numpy_packages_need_no_variant():
    """Mesh tools, grid volumes, cameras and transfer functions work before
    any ``mitsuba.set_variant`` (and the renderer says what it needs)."""
    code = """
import mitsuba as mi
assert mi.variant() is None
import numpy as np
from mi_tetvr.mesh import grid_mesh, build_topology
from mi_tetvr.grid import make_volume
assert make_volume(np.random.rand(4, 5, 6)).values.max() == 1.0
from mi_tetvr.recon import FitConfig, psnr
from mi_tetvr.camera import Camera
from mi_tetvr import TransferFunction
v, t = grid_mesh(2)
assert build_topology(v, t).boundary_faces.shape[1] == 3
cam = Camera.look_at([0, 0, 3], [0, 0, 0], [0, 1, 0], 8, 6, fov_x=40.0)
assert cam.rays()[0].shape[-1] == 3
try:
    import mi_tetvr.render
except ImportError as e:
    assert "set_variant" in str(e)
else:
    raise AssertionError("mi_tetvr.render imported without a variant")
print("ok")
"""
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_library_code_leaves_the_matplotlib_backend_alone():
    """Plots are drawn on ``matplotlib.figure.Figure`` objects: no module of the package
    picks a backend or imports pyplot (which would change a notebook's or an
    application's backend)."""
    said = [f"{p.relative_to(ROOT)}" for p in (ROOT / "mi_tetvr").rglob("*.py")
            if "matplotlib.use(" in p.read_text() or "pyplot" in p.read_text()]
    assert not said, said
