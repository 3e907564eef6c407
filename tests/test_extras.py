"""The core and its extras: ``import mi_tetvr`` imports no optional package, every
import of one sits in ``needs(extra, ...)`` naming an extra that brings it, and a
command whose extra is missing says so in one line."""
import ast
import subprocess
import sys

import pytest

from mi_tetvr.extras import PACKAGES as OPTIONAL
from tests.helpers import ROOT, VARIANT

try:
    import tomllib
except ImportError:                      # Python 3.10
    tomllib = None


def extras_of_pyproject():
    """``{extra: set of PyPI names}``, an extra's references to others resolved."""
    if tomllib is None:
        pytest.skip("tomllib needs Python 3.11")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    raw = project["optional-dependencies"]

    def names(extra, seen=()):
        out = set()
        for req in raw[extra]:
            name = req.split(";")[0].split(">")[0].split("=")[0].split("~")[0].strip()
            if name.startswith("mi_tetvr["):
                for other in name[len("mi_tetvr["):-1].split(","):
                    out |= names(other, seen + (extra,))
            else:
                out.add(name.split("[")[0].lower())
        return out
    return {extra: names(extra) for extra in raw}, project["dependencies"]


def test_the_core_is_small():
    """The core's requirements: Mitsuba (which brings its Dr.Jit), numpy, meshio, tqdm
    and packaging (which reads the supported Mitsuba range at import); Mitsuba by a
    compatible release, not an exact pin."""
    _, core = extras_of_pyproject()
    names = {c.split(">")[0].split("~")[0].split("=")[0].strip() for c in core}
    assert names == {"mitsuba", "numpy", "meshio", "tqdm", "packaging"}
    assert "mitsuba~=3.9.1" in core


def _needs_blocks(tree):
    """``{id(import node): extra}`` of the imports inside ``with needs(extra, ...)``, and
    ``"fallback"`` for those inside a ``try`` that catches ``ImportError`` (one of
    several packages tried in turn)."""
    inside = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(
                getattr(h.type, "id", "") in ("ImportError", "ModuleNotFoundError")
                for h in node.handlers):
            for sub in node.body:
                for leaf in ast.walk(sub):
                    if isinstance(leaf, (ast.Import, ast.ImportFrom)):
                        inside[id(leaf)] = "fallback"
        if isinstance(node, ast.With):
            for item in node.items:
                call = item.context_expr
                if isinstance(call, ast.Call) and getattr(call.func, "id", "") == "needs":
                    extra = getattr(call.args[0], "value", None)   # (a name: no import)
                    for sub in ast.walk(node):
                        if isinstance(sub, (ast.Import, ast.ImportFrom)):
                            inside[id(sub)] = extra
    return inside


def _optional_imports(path):
    """``(line, module, extra or None)`` of every import of an optional package in
    ``path``; ``extra`` is that of the ``needs`` block around it."""
    tree = ast.parse(path.read_text())
    inside = _needs_blocks(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            mods = [node.module]
        else:
            continue
        for mod in mods:
            top = mod.split(".")[0]
            if top in OPTIONAL:
                yield node.lineno, top, inside.get(id(node))


def test_every_optional_import_names_an_extra_that_brings_it():
    """Every import of an optional package in the package (at any depth) is inside
    ``needs(extra, ...)``, and that extra's requirements in pyproject.toml bring it;
    none is imported at a module's top. The decoders tried in turn (``try: import av
    / except ImportError``) are the exception."""
    extras, _ = extras_of_pyproject()
    bad = []
    for path in sorted((ROOT / "mi_tetvr").rglob("*.py")):
        for line, top, extra in _optional_imports(path):
            where = f"{path.relative_to(ROOT)}:{line} imports {top}"
            if extra == "fallback":
                continue
            if extra is None:
                bad.append(f"{where} outside needs(...)")
            elif OPTIONAL[top] not in extras[extra] and not (
                    top == "vtkmodules" and "pyvista" in extras[extra]):
                bad.append(f"{where} in needs({extra!r}), whose requirements lack "
                           f"{OPTIONAL[top]}")
    assert not bad, bad
    assert set(extras) >= {"recon", "sfm", "tomo", "vis", "viewer", "cluster", "all", "test",
                           "docs"}
    assert extras["all"] >= set().union(*(extras[e] for e in ("recon", "sfm", "tomo", "vis",
                                                               "viewer", "cluster")))


def test_the_check_sees_an_import_outside_needs(tmp_path):
    """The check itself: an optional import outside ``needs`` and one inside."""
    p = tmp_path / "x.py"
    p.write_text("import numpy\ndef f():\n    import scipy.sparse\n"
                 "def g():\n    with needs('recon', 'g'):\n        from skimage import io\n"
                 "try:\n    import av\nexcept ImportError:\n    av = None\n")
    assert sorted(_optional_imports(p)) == [(3, "scipy", None), (6, "skimage", "recon"),
                                          (8, "av", "fallback")]


def test_import_mi_tetvr_imports_no_extra():
    """``import mi_tetvr`` imports no optional package: without a variant, with one
    (every plugin registered) and after rendering a tet mesh from arrays."""
    code = f"""
import sys
import mitsuba as mi
import mi_tetvr
import mi_tetvr.mesh, mi_tetvr.transfer, mi_tetvr.camera
before = set(sys.modules)
mi.set_variant({VARIANT!r})
from mi_tetvr.mesh import grid_mesh
v, t = grid_mesh(2)
scene = mi.load_dict({{"type": "scene", "integrator": {{"type": "tetvr"}},
                      "sensor": {{"type": "perspective", "film": {{"type": "hdrfilm",
                                 "width": 4, "height": 4}}}},
                      "volume": mi_tetvr.tetmesh_dict(v, t)}})
mi.render(scene)
optional = {sorted(set(OPTIONAL))!r}
loaded = sorted(m for m in sys.modules if m.split(".")[0] in optional)
print(loaded)
"""
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", f"import mi_tetvr imported {r.stdout.strip()}"


# -- a missing extra, as a user meets it -------------------------------------------------
@pytest.fixture
def hide(monkeypatch):
    """``hide(*names)``: those packages (and their loaded submodules) cannot be imported."""
    def hide(*names):
        for name in names:
            for m in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
                monkeypatch.delitem(sys.modules, m)
            monkeypatch.setitem(sys.modules, name, None)
    return hide


def fails(argv):
    from mi_tetvr import cli
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    return e.value.code


@pytest.mark.parametrize("extra, hidden, argv", [
    ("viewer", "viser", ["view", "{d}"]),
    ("cluster", "ray", ["sweep", "{d}", "{d}/sweep.yaml", "-o", "{d}/out"]),
    ("sfm", "pycolmap", ["process-data", "{d}", "-o", "{d}/out"]),
    ("tomo", "h5py", ["process-xray", "{d}/scan.h5", "-o", "{d}/out"]),
    ("recon", "skimage", ["fit", "{d}", "-o", "{d}/out"]),
    ("vis", "matplotlib", ["viewpoint", "{d}/m.vtu", "-o", "{d}/out"]),
    ("cluster", "ray", ["render", "{d}/m.pvtu", "-o", "{d}/x.png", "--workers", "2"]),
])
def test_a_command_whose_extra_is_missing_says_which_in_one_line(tmp_path, hide, extra,
                                                                  hidden, argv):
    """Each command that needs an extra, its package hidden: one line, ``mi-tetvr: ...
    needs 'PACKAGE' ...: pip install "mi_tetvr[EXTRA]"``, before any work (the files
    it names need not exist)."""
    hide(hidden)
    msg = fails([a.format(d=tmp_path) for a in argv])
    assert isinstance(msg, str) and "\n" not in msg, msg
    assert msg.startswith("mi-tetvr: ") and f"'{OPTIONAL[hidden]}'" in msg, msg
    assert msg.endswith(f'pip install "mi_tetvr[{extra}]"'), msg


def test_a_function_whose_extra_is_missing_says_which(hide):
    """Python users meet the same message, as :class:`MissingExtra` (a
    ``ModuleNotFoundError``): a colormap by name needs matplotlib, fTetWild's mesh
    pytetwild."""
    import numpy as np

    from mi_tetvr.extras import MissingExtra
    from mi_tetvr.mesh.initial import tetwild_init
    from mi_tetvr.transfer import colormap, read_transfer_function
    hide("matplotlib", "pytetwild")
    with pytest.raises(MissingExtra, match=r"^a matplotlib colormap by name needs "
                                           r"'matplotlib', .*\"mi_tetvr\[vis\]\"$"):
        colormap("viridis")
    with pytest.raises(ModuleNotFoundError, match=r'mi_tetvr\[recon\]'):
        tetwild_init(bounds=(np.zeros(3), np.ones(3)))
    # a preset of the package needs nothing more
    assert read_transfer_function("default").opacities.max() > 0


def test_needs_lets_the_projects_own_modules_through():
    """A module of the project that is missing is a bug, not an extra: passed on."""
    from mi_tetvr.extras import MissingExtra, needs
    with pytest.raises(ModuleNotFoundError) as e:
        with needs("recon", "x"):
            import mi_tetvr.no_such_module  # noqa: F401
    assert not isinstance(e.value, MissingExtra)
    with pytest.raises(ValueError, match="unknown extra"):
        with needs("gui", "x"):
            pass
