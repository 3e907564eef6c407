"""The package layout: every exported name resolves, and the numpy
sub-packages import and run without a Mitsuba variant."""
import ast
import importlib
import subprocess
import sys

import pytest

from tests.helpers import ROOT

PACKAGES = ["mi_tetvr", "mi_tetvr.mesh", "mi_tetvr.render", "mi_tetvr.grid", "mi_tetvr.recon",
            "mi_tetvr.apps"]

#: The layers, lowest first: a module imports only from its own layer and those below.
#: The plugins (``mi_tetvr.plugins``) are the top one: they may import any of mi_tetvr's
#: modules, and none of those imports them (the package's ``__init__`` registers them).
LAYERS = [("mi_tetvr.color", "mi_tetvr.transfer", "mi_tetvr.camera", "mi_tetvr.progress",
           "mi_tetvr.video", "mi_tetvr._lazy", "mi_tetvr.cluster", "mi_tetvr.extras"),
          ("mi_tetvr.mesh",), ("mi_tetvr.render",), ("mi_tetvr.grid",), ("mi_tetvr.recon",),
          ("mi_tetvr.apps", "mi_tetvr.distributed"), ("mi_tetvr.cli",), ("mi_tetvr.plugins",)]


def _layer(module):
    for rank, names in enumerate(LAYERS):
        if any(module == n or module.startswith(n + ".") for n in names):
            return rank
    return None


def _module_name(path):
    """The dotted name ``path`` (a file of mi_tetvr/) is imported as."""
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _imported_names(path, module, typing=True):
    """Every module ``path`` imports (also inside functions), relative imports
    resolved; ``from a import b`` names ``a.b`` (b a module or a name in ``a``).
    ``typing=False``: not those under ``if TYPE_CHECKING:`` (never run)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text())
    hints = set() if typing else {
        id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
        and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"
        for n in ast.walk(node)}
    for node in ast.walk(tree):
        if id(node) in hints:
            continue
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            yield from (f"{base}.{a.name}" for a in node.names)


def _layer_violations(files):
    bad = []
    for path in files:
        module = _module_name(path)
        rank = _layer(module)
        if rank is None:             # the package's own __init__ (registration, exports)
            continue
        for name in _imported_names(path, module):
            other = _layer(name)
            if other is not None and other > rank:
                bad.append(f"{module} imports {name}")
    return bad


def _package_files():
    return sorted((ROOT / "mi_tetvr").rglob("*.py"))


def test_no_module_imports_a_layer_above_its_own():
    """Every import of mi_tetvr's modules and plugins (also those inside functions,
    and relative ones) reaches its own layer or one below: the numpy utilities,
    mesh, render, grid, recon, apps, cli, plugins."""
    bad = _layer_violations(_package_files())
    assert not bad, bad


def _import_cycles(files):
    """The cycles of the modules' imports (also those inside functions, which run when
    called; not those for type hints only), each as its sorted module names: the strongly
    connected components of the import graph with more than one module."""
    modules = {_module_name(p): p for p in files}
    graph = {}
    for module, path in modules.items():
        targets = set()
        for name in _imported_names(path, module, typing=False):
            while name and name not in modules:       # a name in a module: the module
                name = name.rpartition(".")[0]
            if name and name != module:
                targets.add(name)
        graph[module] = targets
    # Tarjan's strongly connected components, iteratively
    index, low, stack, on_stack, cycles, count = {}, {}, [], set(), [], 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = count
        count += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, edges = work[-1]
            w = next(edges, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = count
                    count += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    return cycles


def test_no_import_cycle():
    """No two modules of the package import each other, directly or round a loop, counting
    the imports made inside functions (those hide a cycle from Python until they run)."""
    assert _import_cycles(_package_files()) == []


def test_the_cycle_check_sees_a_cycle_through_a_function(tmp_path, monkeypatch):
    """The check itself: a loop closed by an import inside a function is reported, one
    closed only by a type hint's import is not."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "mi_tetvr" / "recon").mkdir(parents=True)
    a, b, c = (tmp_path / "mi_tetvr" / "recon" / f"{n}.py" for n in "abc")
    a.write_text("from mi_tetvr.recon.b import f\n")
    b.write_text("def f():\n    from mi_tetvr.recon import c\n")
    c.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                 "    from mi_tetvr.recon.a import x\n")
    assert _import_cycles([a, b, c]) == []
    c.write_text("def g():\n    from mi_tetvr.recon.a import x\n")
    assert _import_cycles([a, b, c]) == [["mi_tetvr.recon.a", "mi_tetvr.recon.b",
                                           "mi_tetvr.recon.c"]]


@pytest.mark.parametrize("source, module, expected", [
    ("from mi_tetvr.render.walk import trace\n", "mi_tetvr/mesh/x.py", ["mi_tetvr.mesh.x"]),
    ("from ..apps import framing\n", "mi_tetvr/render/x.py", ["mi_tetvr.render.x"]),
    ("from mi_tetvr import plugins\n", "mi_tetvr/cli/x.py", ["mi_tetvr.cli.x"]),
    ("import mi_tetvr.plugins.tetvr\n", "mi_tetvr/apps/x.py", ["mi_tetvr.apps.x"]),
    ("from mi_tetvr.apps import framing\nfrom .tetmesh import TetMeshShape\n",
     "mi_tetvr/plugins/x.py", []),
    ("def f():\n    from mi_tetvr.plugins.tetmesh import TetMeshShape\n",
     "mi_tetvr/recon/x.py", ["mi_tetvr.recon.x"]),
    ("from . import walk\nfrom mi_tetvr.mesh import TetMesh\n", "mi_tetvr/render/x.py", []),
])
def test_the_layer_check_sees_an_import_from_above(tmp_path, monkeypatch, source, module,
                                                    expected):
    """The check itself: imports from a layer above (absolute, relative, of a
    package's attribute, of the plugins) are reported; those below are not."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    path = tmp_path / module
    path.parent.mkdir(parents=True)
    path.write_text(source)
    assert sorted({b.split(" imports ")[0] for b in _layer_violations([path])}) == expected


def architecture_entries(page_text):
    """The modules the documentation's *Architecture* page names, as paths from the
    repository root: the first code block of the page is a tree, one entry a
    line, two spaces of indent a level, ``name.py`` a module and ``name/`` a
    package (which names its ``__init__.py``), each followed by what it does.

    Raises
    ------
    ValueError
        Where the block is missing or a line is not such an entry.
    """
    import re
    block = re.search(r"^```\n(.*?)^```", page_text, re.S | re.M)
    if not block:
        raise ValueError("the Architecture page has no code block")
    entries, parents = set(), []
    for line in block.group(1).splitlines():
        m = re.fullmatch(r"( *)([\w.]+(?:/|\.py)) {2,}\S.*", line)
        depth = m and len(m.group(1)) // 2
        if not m or len(m.group(1)) % 2 or depth > len(parents) or (
                depth > 0 and not parents[depth - 1].endswith("/")):
            raise ValueError(f"not an entry of the tree (NAME.py or NAME/, indented by "
                             f"two spaces a level under a package, then what it does): "
                             f"{line!r}")
        parents[depth:] = [m.group(2)]
        path = "".join(parents)
        entries.add(path + "__init__.py" if path.endswith("/") else path)
    return entries


def _module_files():
    return {str(p.relative_to(ROOT)) for p in _package_files() if "__pycache__" not in p.parts}


def test_only_the_registration_imports_the_plugins():
    """Nothing in the package imports a plugin module but the package's ``__init__``
    (the registration) and the plugins themselves (also inside functions)."""
    said = []
    for path in _package_files():
        module = _module_name(path)
        if module == "mi_tetvr" or module.startswith("mi_tetvr.plugins"):
            continue
        said += [f"{module} imports {name}" for name in _imported_names(path, module)
                 if name == "mi_tetvr.plugins" or name.startswith("mi_tetvr.plugins.")]
    assert not said, said
    names = set(_imported_names(ROOT / "mi_tetvr" / "__init__.py", "mi_tetvr"))
    assert {n for n in names if n.startswith("mi_tetvr.plugins")} <= {
        "mi_tetvr.plugins.register", "mi_tetvr.plugins.on_variant_change",
        "mi_tetvr.plugins.mark", "mi_tetvr.plugins.raised_in"}


def test_the_architecture_page_names_every_module():
    """The documentation's *Architecture* tree names every module of mi_tetvr/ as the
    tree holds them now, and nothing else."""
    named = architecture_entries((ROOT / "docs" / "architecture.md").read_text())
    files = _module_files()
    assert not files - named, (f"modules docs/architecture.md does not name "
                               f"(add a line for each): {sorted(files - named)}")
    assert not named - files, (f"modules docs/architecture.md names that do "
                               f"not exist: {sorted(named - files)}")


def test_the_architecture_tree_is_read_as_written():
    """The tree's reading: nesting by indent, packages by their __init__.py,
    and lines that are not entries refused."""
    text = ("## Architecture\n\n```\nmi_tetvr/    the package\n  a.py       one\n"
            "  sub/       a package\n    b.py     two\n  c.py       three\n"
            "plugins/     plugins\n  d.py       four\n```\n\nmore.py is prose\n## Next\n")
    assert architecture_entries(text) == {
        "mi_tetvr/__init__.py", "mi_tetvr/a.py", "mi_tetvr/sub/__init__.py",
        "mi_tetvr/sub/b.py", "mi_tetvr/c.py", "plugins/__init__.py", "plugins/d.py"}
    for bad in ("  a.py       wrapped\n    on two lines\n",   # a description's second line
                "  a.py\n",                                  # no description
                "  a.py       one\n      b.py   too deep\n",  # under a module
                "   a.py      odd indent\n"):
        with pytest.raises(ValueError, match="not an entry"):
            architecture_entries("## Architecture\n```\nmi_tetvr/   pkg\n" + bad + "```\n## N\n")


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


def test_no_function_of_the_renderer_takes_more_than_8_parameters():
    """The walk's state travels in structures (the ray frame, the cursor,
    the piece, the accumulators): no function or method in ``render/`` or
    ``plugins/`` takes more than 8 parameters (``self`` not counted)."""
    too_many = []
    for path in sorted((ROOT / "mi_tetvr" / "render").glob("*.py")) + sorted(
            (ROOT / "mi_tetvr" / "plugins").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
                names += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
                if names[:1] in (["self"], ["cls"]):
                    names = names[1:]
                if len(names) > 8:
                    too_many.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} "
                                    f"({len(names)})")
    assert not too_many, too_many


def test_no_function_of_the_fit_has_more_than_60_lines_of_code():
    """The fit is written as parts (data, field, strategy, trainer): no function or
    method in ``recon/`` has more than 60 lines besides its docstring (counted as
    ``benchmarks/function_lengths.py`` counts them)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from function_lengths import lengths
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    rows = lengths(ROOT / "mi_tetvr" / "recon")
    assert len(rows) > 300 and rows[0][0] > 40          # it reads the functions
    assert not [r for r in rows if r[0] > 60], [r for r in rows if r[0] > 60]


def test_the_renderer_and_plugins_public_functions_are_typed():
    """The public functions and methods of ``render/`` and ``plugins/`` (module-level
    functions and the methods of module-level classes whose names do not start with
    ``_``, ``__init__`` included) have an annotation on every parameter but ``self``
    and ``cls`` and a return annotation, so that what travels through the walk is
    stated where it is taken and given."""
    missing = []
    for path in sorted((ROOT / "mi_tetvr" / "render").glob("*.py")) + sorted(
            (ROOT / "mi_tetvr" / "plugins").glob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.FunctionDef):
                items = [node]
            elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                items = [m for m in node.body if isinstance(m, ast.FunctionDef)]
            else:
                items = []
            for f in items:
                if f.name.startswith("_") and f.name != "__init__":
                    continue
                a = f.args
                args = [x for x in a.posonlyargs + a.args + a.kwonlyargs
                        if x.arg not in ("self", "cls")]
                untyped = [x.arg for x in args if x.annotation is None]
                if untyped or f.returns is None:
                    missing.append(f"{path.relative_to(ROOT)}:{f.lineno} {f.name}: {untyped} "
                                   f"return={'ok' if f.returns else 'missing'}")
    assert not missing, missing
