"""The package as users get it: ``python -m build`` makes an sdist and a wheel; the
wheel, installed with no extras into a fresh virtual environment, renders a tet mesh
built from arrays and takes its gradient through ``dr.backward`` from a folder outside
the checkout, and each command that needs an extra says which, in one line.

pip takes the core's requirements (Mitsuba, Dr.Jit, numpy, meshio, tqdm) from its
index or its cache."""
import json
import os
import subprocess
import sys
import tarfile
import zipfile

import pytest

from tests.helpers import ROOT, VARIANT


def run(argv, **kwargs):
    return subprocess.run([str(a) for a in argv], capture_output=True, text=True, **kwargs)


@pytest.fixture(scope="module")
def dist(tmp_path_factory):
    """The sdist and the wheel ``python -m build`` makes of the checkout."""
    out = tmp_path_factory.mktemp("dist")
    r = run([sys.executable, "-m", "build", "--outdir", out, ROOT])
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    wheel, = out.glob("mi_tetvr-*.whl")
    sdist, = out.glob("mi_tetvr-*.tar.gz")
    return wheel, sdist


@pytest.fixture(scope="module")
def venv(dist, tmp_path_factory):
    """A fresh virtual environment with the wheel installed, no extras; its ``bin``."""
    env = tmp_path_factory.mktemp("venv")
    r = run([sys.executable, "-m", "venv", env])
    assert r.returncode == 0, r.stderr
    r = run([env / "bin" / "python", "-m", "pip", "install", "-q", dist[0]])
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return env / "bin"


def test_the_wheel_holds_the_package_and_no_more(dist):
    """The plugins inside the package, the bundled scenes and transfer functions, the
    license; no tests, benchmarks or tutorials. The sdist has the package, the license,
    the changelog and the citation file, and no tests (they need the repository)."""
    import mi_tetvr
    wheel, sdist = dist
    assert wheel.name.startswith(f"mi_tetvr-{mi_tetvr.__version__}-py3-none-any")
    names = zipfile.ZipFile(wheel).namelist()
    for needed in ("mi_tetvr/plugins/tetmesh.py", "mi_tetvr/plugins/tetvr.py",
                   "mi_tetvr/extras.py", "mi_tetvr/scenes/default.xml",
                   "mi_tetvr/scenes/tf_default.json"):
        assert needed in names, needed
    assert any(n.endswith(".dist-info/licenses/LICENSE") or n.endswith(".dist-info/LICENSE")
               for n in names)
    tops = {n.split("/")[0] for n in names}
    assert tops == {"mi_tetvr", f"mi_tetvr-{mi_tetvr.__version__}.dist-info"}, tops
    with tarfile.open(sdist) as tar:
        members = {m.split("/", 1)[-1] for m in tar.getnames()}
    assert {"LICENSE", "CHANGELOG.md", "CITATION.cff", "pyproject.toml",
            "mi_tetvr/plugins/tetmesh.py", "mi_tetvr/scenes/default.xml"} <= members
    assert not any(m.startswith("tests/") for m in members)


RENDER = """
import importlib.metadata, json, sys
import numpy as np
import drjit as dr
import mitsuba as mi
mi.set_variant(sys.argv[1])
import mi_tetvr
from mi_tetvr.mesh import grid_mesh

v, t = grid_mesh(3, jitter=0.1, seed=1)
opacity = 1.0 + 0.5 * np.cos(3 * v[:, 0])
color = 0.5 + 0.4 * np.sin(2 * v)
scene = mi.load_dict({
    "type": "scene", "integrator": {"type": "tetvr"},
    "sensor": {"type": "perspective", "fov": 40,
               "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
               "film": {"type": "hdrfilm", "width": 24, "height": 24}},
    "volume": mi_tetvr.tetmesh_dict(v, t, color, opacity)})
params = mi.traverse(scene)
key = "volume.vertex_opacity"
k = int(np.argmin(np.linalg.norm(v - [0.05, 0.05, 0.4], axis=1)))

def loss():
    return dr.sum(mi.render(scene, params, spp=1).array)

dr.enable_grad(params[key])
L = loss()
dr.backward(L)
grad = float(dr.grad(params[key])[k])
h, values = 1e-2, np.array(params[key])
diffs = []
for s in (1, -1):
    moved = values.copy(); moved[k] += s * h
    params[key] = mi.Float(moved); params.update()
    diffs.append(float(loss()[0]))
fd = (diffs[0] - diffs[1]) / (2 * h)
optional = ("scipy", "skimage", "PIL", "matplotlib", "pyvista", "vtkmodules", "trimesh",
            "pytetwild", "pycolmap", "h5py", "algotom", "astra", "viser", "ray", "yaml")
print(json.dumps({"grad": grad, "fd": fd, "image": float(L[0]),
                  "file": mi_tetvr.__file__, "version": mi_tetvr.__version__,
                  "metadata": importlib.metadata.version("mi_tetvr"),
                  "extras_imported": sorted(m for m in sys.modules
                                            if m.split(".")[0] in optional)}))
"""


@pytest.fixture
def outside(tmp_path):
    """A folder outside the checkout, and an environment that does not point into it."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return tmp_path, env


def test_the_wheel_renders_and_differentiates_outside_the_checkout(venv, outside):
    """In the fresh environment, from a folder outside the checkout: a tet mesh from
    arrays renders, and ``dr.backward``'s derivative of the image's sum with respect
    to one vertex's opacity matches a central difference; nothing optional is
    imported and the version is the package's."""
    cwd, env = outside
    r = run([venv / "python", "-c", RENDER, VARIANT], cwd=cwd, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["file"].startswith(str(venv.parent)), out["file"]
    assert out["version"] == out["metadata"]
    assert out["extras_imported"] == []
    assert out["image"] > 0 and abs(out["grad"]) > 1e-3
    assert out["grad"] == pytest.approx(out["fd"], rel=2e-2, abs=1e-4)


def test_the_core_commands_run_and_the_others_name_their_extra(venv, outside):
    """``mi-tetvr`` of the core: the bundled scenes written, a scene and a scalar mesh
    rendered, data sets of a mesh and X-ray projections made; each command that needs an
    extra, one line naming it, exit status 1, no traceback."""
    cwd, env = outside
    cli = venv / "mi-tetvr"
    r = run([cli, "make-scenes", "-o", "scenes"], cwd=cwd, env=env)
    assert r.returncode == 0 and (cwd / "scenes" / "meshes" / "blob.vtu").is_file(), r.stderr
    for argv in (["render", "scenes/default.xml", "-o", "default.png", "--res", "16"],
                 ["render", "scenes/meshes/radial_scalar.vtu", "--tf", "radial", "-o",
                  "radial.exr", "--res", "16"],
                 ["make-dataset", "scenes/meshes/radial_scalar.vtu", "--tf", "radial", "-o",
                  "mesh_data", "--views", "2", "--test-views", "1", "--res", "8", "-q"],
                 ["make-dataset", "scenes/volumes/default.npy", "--xray", "-o", "xray_data",
                  "--views", "2", "--test-views", "1", "-q"]):
        r = run([cli] + argv + ["--variant", VARIANT], cwd=cwd, env=env)
        assert r.returncode == 0 and (cwd / argv[argv.index("-o") + 1]).exists(), r.stderr
    for extra, argv in [
            ("recon", ["fit", "data", "-o", "fit"]),
            ("recon", ["make-dataset", "scenes/volumes/default.npy", "--tf", "default", "-o",
                       "grid_data"]),
            ("sfm", ["process-data", "photos", "-o", "data"]),
            ("tomo", ["process-xray", "scan.h5", "-o", "data"]),
            ("vis", ["render", "scenes/meshes/radial_scalar.vtu", "--tf", "viridis", "-o",
                     "x.png", "--res", "8", "--variant", VARIANT]),
            ("viewer", ["view", "scenes/meshes/blob.vtu"]),
            ("cluster", ["sweep", "data", "sweep.yaml", "-o", "sweep"])]:
        r = run([cli] + argv, cwd=cwd, env=env)
        said = r.stderr.strip()
        assert r.returncode == 1 and "\n" not in said and "Traceback" not in said, said
        assert said.startswith("mi-tetvr: ") and said.endswith(
            f'pip install "mi_tetvr[{extra}]"'), (argv, said)


def test_the_version_is_said_once_and_agreed_with():
    """The version lives in ``mi_tetvr.__version__`` (pyproject.toml reads it); the
    citation file and the changelog's newest entry name the same."""
    import re

    import mi_tetvr
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'dynamic = ["version"]' in pyproject and "mi_tetvr.__version__" in pyproject
    cff = re.search(r"^version: (\S+)$", (ROOT / "CITATION.cff").read_text(), re.M)
    assert cff and cff.group(1) == mi_tetvr.__version__
    newest = re.search(r"^## (\S+) \(", (ROOT / "CHANGELOG.md").read_text(), re.M)
    assert newest and newest.group(1) == mi_tetvr.__version__
