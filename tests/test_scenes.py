"""Scenes the project builds itself: the ``tetmesh`` shape built in Python
(:func:`mi_tetvr.tetmesh_shape`) with the topology handed to it, and a plugin's
refusal as its own exception when Mitsuba builds the scene."""
import subprocess
import sys

import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
import mi_tetvr.mesh.topology
from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import ROOT, VARIANT, rays_at, render_rays


@pytest.fixture(scope="module")
def arrays():
    """A jittered 3^3 grid with three tets listed inverted (re-oriented by
    the topology: its tets differ from the arrays'), random colors and opacities."""
    v, t = grid_mesh(3, jitter=0.15, seed=1)
    t = t.copy()
    t[[0, 7, 20]] = t[[0, 7, 20]][:, [1, 0, 2, 3]]
    rng = np.random.default_rng(3)
    return v, t, rng.uniform(0, 1, (len(v), 3)), rng.uniform(0, 3, len(v))


def scene_of(volume):
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"}, "volume": volume})


def no_topology_built(monkeypatch):
    """Every topology built from here on raises (however build_topology was imported)."""
    def refuse(*args, **kwargs):
        raise AssertionError("topology built again")
    monkeypatch.setattr(mi_tetvr.mesh.topology, "_build_topology", refuse)


def test_a_handed_topology_is_not_built_again(arrays, monkeypatch):
    """A shape built from a TetMesh (its topology), or from a dict entry and the
    topology of its arrays, builds no topology, is named by its key in the scene,
    and renders what the same arrays loaded by Mitsuba render."""
    v, t, color, opacity = arrays
    o, d = rays_at(np.random.default_rng(0), 200)
    with pytest.warns(UserWarning, match="re-oriented"):
        loaded = scene_of(mi_tetvr.tetmesh_dict(v, t, color, opacity))
    expected = render_rays(loaded, o, d)
    assert expected[1].max() > 0.5          # the rays see the volume
    with pytest.warns(UserWarning, match="re-oriented"):
        mesh = mi_tetvr.TetMesh(v, t, color, opacity)
        topology = mesh.topology
    oriented = mi_tetvr.tetmesh_dict(v, topology.tets, color, opacity)

    no_topology_built(monkeypatch)
    with pytest.raises(AssertionError, match="built again"):     # the guard holds
        mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(v, t, color, opacity))
    for shape in (mi_tetvr.tetmesh_shape(mesh),
                  mi_tetvr.tetmesh_shape(oriented, topology=topology)):
        scene = scene_of(shape)
        assert scene.shapes()[0].id() == "volume"
        assert sorted(mi.traverse(scene).keys()) == sorted(mi.traverse(loaded).keys())
        rgb, alpha = render_rays(scene, o, d)
        np.testing.assert_allclose(rgb, expected[0], atol=1e-6)
        np.testing.assert_allclose(alpha, expected[1], atol=1e-6)


def test_a_handed_topology_must_be_that_of_the_arrays(arrays):
    v, t, color, opacity = arrays
    other = mi_tetvr.build_topology(*grid_mesh(2), warn=False)
    with pytest.raises(ValueError, match="not that of these tets"):
        mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(v, t, color, opacity), topology=other)
    with pytest.raises(ValueError, match="not with a 'filename'"):
        mi_tetvr.tetmesh_shape({"type": "tetmesh", "filename": "x.vtu"}, topology=other)


def test_a_built_shape_reads_its_properties_as_mitsuba_does():
    """Properties are checked as ``mi.load_dict`` checks them: one the shape
    does not read is refused (``repair`` is read with a file only), and the
    shape's own checks raise their ValueError."""
    small = mi_tetvr.TetMesh(*grid_mesh(1))
    with pytest.raises(RuntimeError, match="unreferenced property") as by_mitsuba:
        mi.load_dict(mi_tetvr.tetmesh_dict(small.vertices, small.tets, repair=True))
    with pytest.raises(RuntimeError, match="unreferenced property") as built:
        mi_tetvr.tetmesh_shape(small, repair=True)
    assert str(built.value) == str(by_mitsuba.value)
    with pytest.raises(ValueError, match=r"^tetmesh: model must be one of"):
        mi_tetvr.tetmesh_shape(small, model="xray")
    shape = mi_tetvr.tetmesh_shape(small, model="absorption",
                                   to_world=mi.ScalarTransform4f().translate([0, 0, 2]))
    assert shape.optical_model.__name__ == "Absorption"
    assert np.array(shape.bbox().min) == pytest.approx([-1, -1, 1])


# -- a plugin's refusal, as Python users read it -------------------------------------------
#: Exceptions carry notes (where in the scene a plugin refused it) from Python 3.11 on.
NOTES = sys.version_info >= (3, 11)
SCENE_XML = """<scene version="3.0.0">
    <integrator type="tetvr"/>
    <shape type="tetmesh" id="volume">
        <string name="filename" value="{mesh}"/>{extra}
    </shape>
</scene>
"""


def refusals(scene_dict, xml_path):
    """What each loader raises for a scene: mi_tetvr.load_dict, load_file,
    load_string, ``(exception, its notes)`` each."""
    out = []
    for load in (lambda: mi_tetvr.load_dict(scene_dict), lambda: mi_tetvr.load_file(xml_path),
                 lambda: mi_tetvr.load_string(xml_path.read_text())):
        with pytest.raises(Exception) as e:
            load()
        out.append((e.value, " ".join(getattr(e.value, "__notes__", []))))
    return out


def test_a_folded_mesh_is_refused_in_the_plugins_words(tmp_path):
    """Mitsuba's loader wraps the plugin's MeshError in its own RuntimeError with
    the plugin's traceback as text; the project's loaders raise the MeshError
    itself, its one line, and say in a note where in the scene it was."""
    import meshio
    from tests.mesh.test_io import folded_grid
    v, t = folded_grid()
    meshio.write(tmp_path / "folded.vtu", meshio.Mesh(v, [("tetra", t)]))
    with pytest.raises(mi_tetvr.MeshError) as e:
        mi_tetvr.read_tetmesh(tmp_path / "folded.vtu").topology
    expected = str(e.value)
    assert "folds over itself" in expected and "repair" in expected and "\n" not in expected
    xml = tmp_path / "scene.xml"
    xml.write_text(SCENE_XML.format(mesh=tmp_path / "folded.vtu", extra=""))
    scene = {"type": "scene", "integrator": {"type": "tetvr"},
             "volume": {"type": "tetmesh", "filename": str(tmp_path / "folded.vtu")}}
    with pytest.raises(RuntimeError, match=r"(?s)^\[parser.*Traceback.*folds over itself"):
        mi.load_dict(scene)
    (by_dict, dict_note), (by_file, file_note), (by_string, _) = refusals(scene, xml)
    for err in (by_dict, by_file, by_string):
        assert type(err) is mi_tetvr.MeshError and str(err) == expected
    if NOTES:
        for note in (dict_note, file_note):
            assert note == '(raised by the "tetmesh" plugin while Mitsuba built "volume")'
    for err in (by_dict, by_file, by_string):
        assert err.mi_tetvr_plugin == "tetmesh"
    # the loaders return what Mitsuba's return where nothing is refused
    xml.write_text(SCENE_XML.format(mesh=tmp_path / "folded.vtu",
                                    extra='\n        <boolean name="repair" value="true"/>'))
    with pytest.warns(UserWarning, match="dropped"):
        loaded = mi_tetvr.load_file(xml)
    assert loaded.shapes()[0].tet_count == len(t) - 2


def test_a_constant_scalar_is_refused_in_the_plugins_words(tmp_path):
    """A constant scalar with a transfer function and no value range: refused by
    tetmesh_dict and tetmesh_shape before Mitsuba builds anything, by the loaders
    for an entry made by hand and for a file, each with the shape's one line."""
    import meshio
    v, t = grid_mesh(2)
    tf = str(ROOT / "scenes" / "tf_default.json")
    line = ("tetmesh: the scalar range must have value_min < value_max, got [2.0, 2.0] "
            "(array '{}' is constant: give a range)")
    flat = np.full(len(v), 2.0)
    with pytest.raises(ValueError) as e:
        mi_tetvr.tetmesh_dict(v, t, scalar=flat, transfer_function=tf)
    assert str(e.value) == line.format("scalar")
    # by hand: the same entry as tetmesh_dict's
    entry = {"type": "tetmesh", "vertices": mi.TensorXf(v.astype(np.float32)),
             "tets": mi.TensorXi(t.astype(np.int32)),
             "scalar": mi.TensorXf(flat.astype(np.float32)), "transfer_function": tf}
    with pytest.raises(ValueError) as e:
        mi_tetvr.tetmesh_shape(entry)
    assert str(e.value) == line.format("scalar")
    meshio.write(tmp_path / "flat.vtu", meshio.Mesh(v, [("tetra", t)],
                                                    point_data={"density": flat}))
    xml = tmp_path / "scene.xml"
    xml.write_text(SCENE_XML.format(mesh=tmp_path / "flat.vtu", extra=f"""
        <string name="transfer_function" value="{tf}"/>"""))
    (by_dict, _), (by_file, _), (by_string, _) = refusals({"type": "scene", "v": entry}, xml)
    assert type(by_dict) is ValueError and str(by_dict) == line.format("scalar")
    for err in (by_file, by_string):
        assert type(err) is ValueError and str(err) == line.format("density")
    # with a range it loads
    mi_tetvr.tetmesh_dict(v, t, scalar=flat, transfer_function=tf, value_min=0.0, value_max=4.0)


def test_other_errors_pass_unchanged():
    """Mitsuba's own errors (an unknown plugin, a property no plugin reads) are
    not a plugin's: the loaders raise them as Mitsuba does."""
    for scene in ({"type": "scene", "v": {"type": "tetmeshes"}},
                  {"type": "scene", "v": mi_tetvr.tetmesh_dict(*grid_mesh(1), colour=1.0)}):
        with pytest.raises(RuntimeError) as mitsuba_error:
            mi.load_dict(scene)
        with pytest.raises(RuntimeError) as ours:
            mi_tetvr.load_dict(scene)
        assert str(ours.value) == str(mitsuba_error.value)
    plain = RuntimeError("[parser.cpp:12] no traceback here")
    assert mi_tetvr.plugin_error(plain) is plain
    assert mi_tetvr.plugin_error(ValueError("x")).args == ("x",)


def test_a_nested_plugins_error_is_the_innermost():
    """A plugin that builds another (tetvr and the integrator of its surfaces) passes
    the other's error on inside its own: the loaders raise the innermost plugin's
    exception, with no parsing of Mitsuba's text (each plugin keeps what it raised)."""
    scene = {"type": "scene", "v": mi_tetvr.tetmesh_dict(*grid_mesh(1)),
             "integrator": {"type": "tetvr", "surfaces": {"type": "tetproj",
                                                          "mode": "median"}}}
    with pytest.raises(RuntimeError) as by_mitsuba:
        mi.load_dict(scene)
    with pytest.raises(ValueError) as ours:
        mi_tetvr.load_dict(scene)
    assert type(ours.value) is ValueError and str(ours.value).startswith("tetproj: ")
    assert "\n" not in str(ours.value) and str(ours.value) in str(by_mitsuba.value)
    assert ours.value.mi_tetvr_plugin == "tetproj"
    if NOTES:
        assert ours.value.__notes__ == [
            '(raised by the "tetproj" plugin while Mitsuba built "surfaces")']
    # Mitsuba's own loader's error is read back too, once
    err = mi_tetvr.plugin_error(by_mitsuba.value)
    assert type(err) is ValueError and str(err) == str(ours.value)
    assert mi_tetvr.plugin_error(by_mitsuba.value) is by_mitsuba.value


def test_mitsuba_passes_a_plugins_message_on_in_its_own():
    """What the loaders rely on, in the words of this Mitsuba: the parser's
    ``RuntimeError`` holds the plugin's message as it was raised (where it did not,
    the loaders would still raise the one error a plugin raised during the load)."""
    import mi_tetvr.plugins as plugins
    entry = mi_tetvr.tetmesh_dict(*grid_mesh(1), model="xray")
    since = plugins.mark()
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({"type": "scene", "v": entry})
    err, plugin, where = plugins.raised_in(RuntimeError("a text that holds no message"),
                                           since)
    assert (plugin, where) == ("tetmesh", "v") and type(err) is ValueError
    assert str(err).startswith("tetmesh: model must be one of") and str(err) in str(e.value)


# -- the plugins and the variant ---------------------------------------------------------
SWITCH = """
import subprocess
import sys
import drjit as dr
import mitsuba as mi
import mi_tetvr                         # before any variant: nothing registered yet
from mi_tetvr.mesh import grid_mesh
from mi_tetvr.plugins import registered_variant
assert registered_variant() is None
v, t = grid_mesh(2)

def render():
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "sensor": {"type": "perspective", "film": {"type": "hdrfilm",
                                     "width": 4, "height": 4}},
                          "volume": mi_tetvr.tetmesh_dict(v, t, opacity=v[:, 0] + 1.5)})
    return float(dr.mean(mi.render(scene).array)[0])

out = []
for variant in sys.argv[1:]:
    mi.set_variant(variant)             # the plugins follow by themselves
    out.append(render() if variant.endswith("_ad_rgb") else None)
    print(variant, registered_variant(), out[-1])
first = out[0]
assert all(o is None or abs(o - first) < 1e-5 * abs(first) for o in out), out
"""


@pytest.mark.parametrize("variants", [
    ["llvm_ad_rgb", "scalar_rgb", "llvm_ad_rgb"],
    ["llvm_ad_rgb", "cuda_ad_rgb", "llvm_ad_rgb"]], ids=["llvm-scalar-llvm", "llvm-cuda-llvm"])
def test_the_plugins_follow_the_variant(variants):
    """``import mi_tetvr`` before any variant, then ``mi.set_variant``: the plugins are
    registered with each autodiff RGB variant Mitsuba switches to (the modules bound to
    a variant's types reloaded for a new one), and render the same image in each."""
    import drjit as dr
    if "cuda_ad_rgb" in variants and not dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("no CUDA GPU here: the switch between two autodiff variants runs in "
                    "benchmarks/gpu_check.sh")
    r = subprocess.run([sys.executable, "-c", SWITCH, *variants], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    lines = r.stdout.strip().splitlines()
    assert [line.split()[:2] for line in lines] == [
        [v, v if v.endswith("_ad_rgb") else variants[0]] for v in variants]


REBIND = """
import sys
import types
import drjit as dr
import mitsuba as mi
mi.set_variant(sys.argv[1])
import mi_tetvr
import mi_tetvr.apps.viewpoint, mi_tetvr.grid.marcher, mi_tetvr.recon.trainer  # noqa: E401,F401
from mi_tetvr.mesh import grid_mesh
from mi_tetvr.plugins import rebind, variant_bound_modules
v, t = grid_mesh(2)
s = v[:, 0] + 2 * v[:, 1]


def render():
    film = {"type": "hdrfilm", "width": 4, "height": 4}
    out = []
    for integrator, volume in [
            ({"type": "tetvr"}, mi_tetvr.tetmesh_dict(v, t, opacity=v[:, 0] + 1.5)),
            ({"type": "tetproj", "mode": "max"},
             mi_tetvr.tetmesh_dict(v, t, scalar=s, transfer_function="gray")),
            ({"type": "tetpath", "max_depth": 2},
             mi_tetvr.tetmesh_dict(v, t, opacity=v[:, 0] + 1.5, albedo=0.5))]:
        scene = mi.load_dict({"type": "scene", "integrator": integrator,
                              "sensor": {"type": "perspective", "film": film},
                              "light": {"type": "constant"}, "volume": volume})
        out.append(float(dr.mean(mi.render(scene, seed=1).array)[0]))
    return out


def stale():
    found = []
    for name, module in list(sys.modules.items()):
        if not name.startswith("mi_tetvr") or not isinstance(module, types.ModuleType):
            continue
        for key, value in list(vars(module).items()):
            source = getattr(value, "__module__", None)
            path = getattr(value, "__qualname__", None)
            if (not isinstance(source, str) or not source.startswith("mi_tetvr")
                    or source == name or not isinstance(path, str) or "<" in path):
                continue
            now = sys.modules.get(source)
            for part in path.split("."):
                now = getattr(now, part, None)
            if now is not None and now is not value:
                found.append(f"{name}.{key}")
    return found


before = render()
bound = {m.__name__ for m in variant_bound_modules()}
rebind()
assert not stale(), stale()
after = render()
assert all(abs(a - b) <= 1e-6 * abs(b) for a, b in zip(after, before)), (before, after)
print(len(bound), sorted(bound))
"""


def test_rebinding_for_a_variant_leaves_nothing_stale():
    """What a switch of variant reloads is read from the modules (no list to keep):
    after :func:`mi_tetvr.plugins.rebind`, no module of mi_tetvr holds a function or
    class that its own module has replaced (the former list of 14 modules left 50 such
    names, among them the merged walk's geometry), and the three integrators render as
    before."""
    r = subprocess.run([sys.executable, "-c", REBIND, VARIANT], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    count, names = r.stdout.split(" ", 1)
    assert int(count) >= 20
    for name in ("mi_tetvr.render.walk", "mi_tetvr.render.program", "mi_tetvr.recon.trainer",
                 "mi_tetvr.plugins.tetvr", "mi_tetvr.grid.marcher"):
        assert name in names, name
