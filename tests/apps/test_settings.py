"""Render settings (mi_tetvr.apps.settings.RenderSettings): every combination of options
that is refused gives its message, for a mesh file and for an XML scene, from the settings
and from ``mi-tetvr render``; the combinations next to them are accepted; values from
Python are read as the command line reads them; the render command's options are the
fields."""
import dataclasses

import numpy as np
import pytest

from mi_tetvr.apps.settings import RenderSettings
from tests.helpers import ROOT, VARIANT

XML_WHY = ("to an XML scene (its shapes name their transfer functions, its integrator its "
           "mode and clip)")

# (settings, input: "mesh", "series" or "xml", the message)
REFUSED = [
    (dict(tf="viridis", value_range=(1.0, 0.5)), "mesh",
     "--value-range needs LO < HI, got (1.0, 0.5)"),
    (dict(value_range=(0.0, 1.0)), "mesh", "--value-range is the range of a scalar's transfer "
     "function: it needs --tf (or a projection --mode)"),
    (dict(sensor="v.xml", orbit=4, res=(8, 8)), "mesh", "--sensor says where the camera is "
     "and its film's size; --orbit, --res cannot be combined with it"),
    (dict(sensor="v.xml", view=(10.0, 10.0), up=(0.0, 1.0, 0.0)), "mesh", "--sensor says "
     "where the camera is and its film's size; --view, --up cannot be combined with it"),
    (dict(sensor="v.xml"), "series", "--sensor says where the camera is and its film's size; "
     "a series cannot be combined with it"),
    (dict(orbit=4), "xml", "--orbit circles one mesh file (an XML scene's sensors stay)"),
    (dict(orbit=4), "series", "--orbit circles one mesh file (an XML scene's sensors stay)"),
    (dict(orbit=0), "mesh", "--orbit needs at least 1 frame, got 0"),
    (dict(classification="pre"), "mesh",
     "--classification does not apply to a mesh (its scalar is post-classified)"),
    (dict(scalar="s"), "mesh", "--scalar needs --tf"),
    (dict(shade=True), "mesh", "--shade needs --tf"),
    (dict(shade=True, mode="max"), "mesh", "--shade lights volume rendering (--mode dvr)"),
    (dict(tf="viridis", iso=(0.5,), plane=(0, 0, 0, 0, 0, 1)), "mesh",
     "the volume takes one kind of surface: --iso or --plane"),
    (dict(iso=(0.5,)), "mesh", "--iso or --plane in volume rendering needs --tf (a scalar)"),
    (dict(plane=(0, 0, 0, 0, 0, 1)), "mesh",
     "--iso or --plane in volume rendering needs --tf (a scalar)"),
    (dict(mode="max", iso=(0.5,)), "mesh", "--iso gives the isovalues of --mode iso (or dvr)"),
    (dict(mode="iso", plane=(0, 0, 0, 0, 0, 1)), "mesh",
     "--plane is the plane of --mode slice (or dvr)"),
    (dict(tf="viridis", surface_opacity=0.5), "mesh",
     "--surface-opacity is an opacity in (0, 1] of isosurfaces and slices"),
    (dict(mode="iso", surface_opacity=1.5), "mesh",
     "--surface-opacity is an opacity in (0, 1] of isosurfaces and slices"),
    (dict(mode="slice", surface_opacity=0.0), "mesh",
     "--surface-opacity is an opacity in (0, 1] of isosurfaces and slices"),
    (dict(view=(10.0, 10.0)), "xml",
     "--view frames a mesh file; an XML scene's sensor says where it looks"),
    (dict(view=(10.0, 10.0), up=(0.0, 1.0, 0.0)), "xml",
     "--view, --up frame a mesh file; an XML scene's sensor says where it looks"),
    (dict(tf="viridis"), "xml", f"--tf does not apply {XML_WHY}"),
    (dict(scalar="s", clip_box=(0, 0, 0, 1, 1, 1)), "xml",
     f"--scalar, --clip-box do not apply {XML_WHY}"),
    (dict(plane=(0, 0, 0, 0, 0, 1)), "xml", f"--plane does not apply {XML_WHY}"),
    (dict(clip=(0, 0, 0, 0, 0, 1)), "xml", f"--clip does not apply {XML_WHY}"),
    (dict(iso=(0.5,)), "xml", f"--iso does not apply {XML_WHY}"),
    (dict(shade=True), "xml", f"--shade does not apply {XML_WHY}"),
    (dict(surface_opacity=0.5), "xml", f"--surface-opacity does not apply {XML_WHY}"),
    (dict(value_range=(0.0, 1.0)), "xml", f"--value-range does not apply {XML_WHY}"),
    (dict(opacity_scale=2.0), "xml", "--opacity-scale applies to a mesh file rendered with "
     "--tf"),
    (dict(mode="max"), "xml", "--mode applies to a mesh file (an XML scene names its "
     "integrator: 'tetproj' with its mode)"),
]

# each accepted where the refusals above are near: the checks refuse those only
ACCEPTED = [
    (dict(tf="viridis", value_range=(0.0, 1.0)), "mesh"),
    (dict(mode="max", value_range=(0.0, 1.0)), "mesh"),
    (dict(sensor="v.xml"), "mesh"),
    (dict(sensor="v.xml", spp=4), "xml"),
    (dict(orbit=1, view=(10.0, 5.0), up=(0.0, 1.0, 0.0)), "mesh"),
    (dict(classification="pre", res=(8, 6), spp=2, repair=True), "xml"),
    (dict(tf="viridis", scalar="s", shade=True), "mesh"),
    (dict(mode="min", scalar="s"), "mesh"),
    (dict(tf="viridis", iso=(0.5, 0.7), surface_opacity=0.5), "mesh"),
    (dict(tf="viridis", plane=(0, 0, 0, 0, 0, 1), surface_opacity=1.0), "mesh"),
    (dict(mode="iso", iso=(0.5,)), "mesh"),
    (dict(mode="slice", plane=(0, 0, 0, 1, 0, 0), surface_opacity=0.25), "mesh"),
    (dict(mode="mean", clip=(0, 0, 0, 1, 0, 0), clip_box=(-1, -1, -1, 1, 1, 1)), "mesh"),
    (dict(tf="viridis", opacity_scale=3.0), "mesh"),
    (dict(view=(10.0, 10.0)), "series"),
]


def validate(settings, where):
    settings.validate("mesh" if where != "xml" else "xml", series=where == "series")


@pytest.mark.parametrize("kw,where,message", REFUSED)
def test_each_refused_combination_gives_its_message(kw, where, message):
    with pytest.raises(ValueError) as e:
        validate(RenderSettings(**kw), where)
    assert str(e.value) == message


@pytest.mark.parametrize("kw,where", ACCEPTED)
def test_the_combinations_beside_them_are_accepted(kw, where):
    validate(RenderSettings(**kw), where)


def test_values_from_python_read_as_the_command_line_reads_them():
    s = RenderSettings(iso="0.5,0.75", plane=[0, 0, 1, 0, 0, 1], res=32, value_range="0,2",
                       up=np.array([0, 1, 0]))
    assert s.iso == (0.5, 0.75) and s.plane == (0.0, 0.0, 1.0, 0.0, 0.0, 1.0)
    assert s.res == (32, 32) and s.value_range == (0.0, 2.0) and s.up == (0.0, 1.0, 0.0)
    assert RenderSettings(iso=0.25).iso == (0.25,)
    assert RenderSettings(res="40x30").res == (40, 30)
    # what is not given: render MESH's camera
    assert RenderSettings().azimuth_elevation == (45.0, 30.0)
    assert RenderSettings().up_axis == (0.0, 0.0, 1.0)
    for kw, said in ((dict(plane="0,0,1"), "expected 6 comma-separated numbers"),
                     (dict(up=(0, 0, 0)), "expected a non-zero vector"),
                     (dict(iso="low"), "expected comma-separated numbers"),
                     (dict(res="40by30"), "must be WxH (e.g. 640x480) or N")):
        with pytest.raises(ValueError, match=said.replace("(", r"\(").replace(")", r"\)")):
            RenderSettings(**kw)
    # frozen: a changed setting is a new (checked) object
    with pytest.raises(dataclasses.FrozenInstanceError):
        RenderSettings().mode = "max"
    assert dataclasses.replace(RenderSettings(), view="10,20").view == (10.0, 20.0)


def test_the_render_options_are_the_fields():
    """render's parser has one option per field, with the field's default, and parses a
    command line into the same settings as the fields take from Python."""
    from mi_tetvr import cli
    render = next(a for a in cli.build_parser()._actions if a.dest == "cmd").choices["render"]
    actions = {a.dest: a for a in render._actions}
    for f in dataclasses.fields(RenderSettings):
        assert f.name in actions, f.name
        assert actions[f.name].default == f.default
        assert f.metadata["help"] == actions[f.name].help.replace("%%", "%")
    a = cli.build_parser().parse_args([
        "render", "m.vtu", "-o", "x.png", "--tf", "viridis", "--iso", "0.5,0.75",
        "--clip-box", "0,0,0,1,1,1", "--view", "10,20", "--res", "40x30", "--shade"])
    assert cli.settings_of(RenderSettings, a) == RenderSettings(
        tf="viridis", iso=(0.5, 0.75), clip_box=(0, 0, 0, 1, 1, 1), view=(10, 20),
        res=(40, 30), shade=True)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A scalar mesh file and a second one (a series), and the bundled XML scene."""
    from mi_tetvr.mesh.generate import grid_mesh
    from mi_tetvr.mesh.io import write_tetmesh
    from mi_tetvr.mesh.tetmesh import TetMesh
    d = tmp_path_factory.mktemp("settings")
    v, t = grid_mesh(2)
    paths = []
    for k in range(2):
        paths.append(d / f"m{k}.vtu")
        write_tetmesh(paths[-1], TetMesh(v, t, point_data={"s": v[:, 0] + k}))
    return {"mesh": [str(paths[0])], "series": [str(p) for p in paths],
            "xml": [str(ROOT / "scenes" / "default.xml")]}


def _flags(kw):
    out = []
    for name, value in kw.items():
        flag = "--" + name.replace("_", "-")
        if value is True:
            out.append(flag)
        elif name == "res":
            out += [flag, "x".join(map(str, value))]
        elif isinstance(value, tuple):
            out += [flag, ",".join(repr(float(v)) for v in value)]
        else:
            out += [flag, str(value)]
    return out


@pytest.mark.parametrize("kw,where,message", REFUSED)
def test_render_prints_each_refusal_as_one_line(kw, where, message, inputs, tmp_path):
    """``mi-tetvr render`` with those options: ``mi-tetvr: <the message>``, before it reads
    or renders anything."""
    from mi_tetvr import cli
    with pytest.raises(SystemExit) as e:
        cli.main(["render", *inputs[where], "-o", str(tmp_path / "x.png"), *_flags(kw),
                  "--variant", VARIANT])
    assert e.value.code == f"mi-tetvr: {message}"
    assert not (tmp_path / "x.png").exists()
