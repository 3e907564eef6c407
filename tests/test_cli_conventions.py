"""The command line's conventions and its errors, in process (``mi_tetvr.cli.main``).

Every command accepts the shared flags of what it does (the lists below are this test's
own, written from what each command does, not read from the parser); the fit's options
are FitConfig's fields; bad input ends in one ``mi-tetvr: ...`` line that names the problem
and the way past it, never a traceback.
"""
import json

import numpy as np
import pytest

from mi_tetvr import cli
from mi_tetvr.recon.config import FitConfig
from tests.helpers import ROOT, VARIANT

# positional arguments each command needs to parse
POSITIONAL = {"render": ["s.xml"], "info": ["m.vtu"], "make-scenes": [],
              "make-dataset": ["v.npy"], "make-capture": [], "process-data": ["photos"],
              "process-xray": ["scan.h5"],
              "fit": ["data"], "eval": ["fit", "data"], "uncertainty": ["fit", "data"],
              "next-view": ["fit", "data"], "export": ["m.vtu"], "refine": ["m.vtu"],
              "viewpoint": ["m.vtu"], "view": ["m.vtu"], "partition": ["m.vtu"],
              "sweep": ["data", "sweep.yaml"]}
REQUIRED = {"refine": ["--select", "x"], "partition": ["--blocks", "2"],
            "next-view": ["--candidates", "4"]}
WRITES = set(POSITIONAL) - {"info"}
RENDERS = {"render", "make-dataset", "make-capture", "fit", "eval", "viewpoint", "view",
           "sweep", "uncertainty", "next-view"}
SHOWS_PROGRESS = {"make-dataset", "make-capture", "process-data", "process-xray", "fit",
                  "viewpoint", "partition", "uncertainty", "next-view"}
READS_MESHES = {"render", "info", "make-dataset", "fit", "eval", "export", "refine", "viewpoint",
                "view", "partition"}
MAKES_IMAGES = {"render", "make-dataset", "make-capture", "viewpoint", "view"}


def parse(cmd, *flags):
    out = ["-o", "x"] if cmd in WRITES else []
    return cli.build_parser().parse_args([cmd, *POSITIONAL[cmd], *out, *REQUIRED.get(cmd, []),
                                          *flags])


def fails(argv, capsys=None):
    """Run the command line; the SystemExit's message (or code)."""
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    return e.value.code


def test_the_commands_are_those_listed():
    sub = next(a for a in cli.build_parser()._actions if a.dest == "cmd")
    assert set(sub.choices) == set(POSITIONAL)


@pytest.mark.parametrize("cmd", sorted(POSITIONAL))
def test_every_command_accepts_the_shared_flags(cmd, capsys):
    parser_of = next(a for a in cli.build_parser()._actions if a.dest == "cmd").choices[cmd]
    flags = {s for a in parser_of._actions for s in a.option_strings}
    assert ({"-o", "--out"} <= flags) == (cmd in WRITES)
    assert ("--variant" in flags) == (cmd in RENDERS)
    assert ({"-q", "--quiet"} <= flags) == (cmd in SHOWS_PROGRESS)
    assert ({"--repair", "--cell-to-point"} <= flags) == (cmd in READS_MESHES)
    assert ("--res" in flags) == (cmd in MAKES_IMAGES)
    if cmd in WRITES:
        assert parse(cmd).out in ("x", ["x"])
    if cmd in RENDERS:
        assert parse(cmd, "--variant", "cuda_ad_rgb").variant == "cuda_ad_rgb"
        help = next(a.help for a in parser_of._actions if a.dest == "variant")
        assert "llvm_ad_rgb" in help and "cuda_ad_rgb" in help
    if cmd in SHOWS_PROGRESS:
        assert parse(cmd, "-q").quiet and not parse(cmd).quiet
    if cmd in READS_MESHES:
        a = parse(cmd, "--repair", "--cell-to-point")
        repair = a.cfg_repair if cmd == "fit" else a.repair
        cell = a.cfg_cell_to_point if cmd == "fit" else a.cell_to_point
        assert repair and cell
    if cmd in MAKES_IMAGES:
        assert tuple(parse(cmd, "--res", "40x30").res) == (40, 30)
        assert tuple(parse(cmd, "--res", "32").res) == (32, 32)
        with pytest.raises(SystemExit):
            parse(cmd, "--res", "40by30")
        assert "WxH" in capsys.readouterr().err


def test_one_default_per_quantity():
    """The held-out views of every data set maker, the opacity scale of every command: one
    default each; the Python name the mesh errors give for repairs resolves."""
    import inspect

    from mi_tetvr.mesh import repair_tets  # noqa: F401 (named by MeshError's advice)
    from mi_tetvr.mesh.topology import REPAIR_HINT
    from mi_tetvr.recon import synthetic
    assert "mi_tetvr.mesh.repair_tets" in REPAIR_HINT and "--repair" in REPAIR_HINT
    for maker in (synthetic.make_dataset, synthetic.make_mesh_dataset,
                  synthetic.make_xray_dataset):
        assert inspect.signature(maker).parameters["test_views"].default == cli.TEST_VIEWS
    assert parse("make-dataset").test_views == cli.TEST_VIEWS


def test_version_and_opacity_scale_default(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("mi-tetvr ")
    # one default of the same quantity everywhere
    defaults = {parse(c).opacity_scale for c in ("make-dataset", "viewpoint")}
    assert defaults == {FitConfig().field.opacity_scale} == {cli.OPACITY_SCALE}


def _sample(f):
    """A value for the field ``f`` other than its default, and its command-line text."""
    kind = cli._setting_type(f)
    if "choices" in f.metadata:
        value = next(c for c in f.metadata["choices"] if c != f.default)
        return value, [value]
    special = {"bounds": ([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], ["0,0,0,1,2,3"]),
               "value_range": ([0.0, 2.0], ["0,2"]),
               "stages": ([{"iterations": 3}], ['[{"iterations": 3}]']),
               "background": ([1.0, 1.0, 1.0], ["white"]), "init": ("m.vtu", ["m.vtu"])}
    if f.name in special:
        return special[f.name]
    if kind is bool:
        return (not f.default, [] if not f.default else None)
    if kind is int:
        return 3, ["3"]
    if kind is float:
        return 0.25, ["0.25"]
    return "name", ["name"]


@pytest.mark.parametrize("field", [f.name for _, f in FitConfig.settings()])
def test_every_fit_setting_is_an_option(field):
    """Each FitConfig field has its option, parsed to the field's type, with the help
    written in the field (and its default)."""
    f = next(f for _, f in FitConfig.settings() if f.name == field)
    fit = next(a for a in cli.build_parser()._actions if a.dest == "cmd").choices["fit"]
    action = next(a for a in fit._actions if a.dest == f"cfg_{field}")
    assert f.metadata["help"].split(";")[0] in action.help.replace("%%", "%")
    value, text = _sample(f)
    flag = action.option_strings[0]
    if cli._setting_type(f) is bool:
        argv = [flag] if value else ["--no-" + flag[2:]]
    else:
        argv = [flag, *text]
    extra = []
    if field == "optimize":          # tf needs the scalar mesh
        extra = ["--init", "m.vtu"]
    if field in ("solver", "basis"):  # the linear solvers solve X-ray projections
        extra = ["--model", "absorption"]
    if field == "lights":            # the known lighting of a scattering medium
        extra = ["--model", "scattering"]
    a = parse("fit", *argv, *extra)
    assert cli.fit_config(a).flat()[field] == value


def test_config_file_print_config_and_overrides(tmp_path, capsys):
    # an old flat file, with a setting's earlier name: read, with one line saying so
    (tmp_path / "c.yaml").write_text("lr_color: 0.3\nstages:\n  - iterations: 5\n"
                                     "resolution: 7\n")
    cli.main(["fit", "data", "-o", "out", "--config", str(tmp_path / "c.yaml"),
              "--lr-opacity", "0.4", "--print-config"])
    out = capsys.readouterr()
    assert out.err.strip() == (f"mi-tetvr: warning: {tmp_path / 'c.yaml'}: the setting "
                               f"'resolution' is now 'grid_resolution' (part 'mesh'); read as "
                               f"such")
    cfg = json.loads(out.out)
    assert list(cfg) == ["data", "mesh", "field", "strategy", "trainer"]
    assert cfg["trainer"]["lr_color"] == 0.3 and cfg["trainer"]["lr_opacity"] == 0.4
    assert cfg["strategy"]["stages"] == [{"iterations": 5}]
    assert cfg["mesh"]["grid_resolution"] == 7
    with pytest.warns(UserWarning, match="'resolution' is now 'grid_resolution'"):
        expected = FitConfig.from_file(tmp_path / "c.yaml").updated(lr_opacity=0.4)
    assert cfg == expected.nested()
    # what --print-config prints is a --config file of the same settings
    (tmp_path / "printed.json").write_text(out.out)
    assert FitConfig.from_file(tmp_path / "printed.json") == expected
    for text, said in (('{"lr_colour": 1}', "unknown fit settings 'lr_colour' (did you mean "
                                            "'lr_color'?)"),
                       ('{"trainer": {"grid_resolution": 8}}', "'grid_resolution' is a "
                                                               "setting of part 'mesh', not "
                                                               "'trainer'"),
                       ('{"trainer": {"lr_colour": 1}}', "unknown fit settings "
                                                         "'trainer.lr_colour'")):
        (tmp_path / "bad.json").write_text(text)
        msg = fails(["fit", "d", "-o", "o", "--config", str(tmp_path / "bad.json")])
        assert msg.startswith(f"mi-tetvr: {tmp_path / 'bad.json'}: {said}"), msg
    (tmp_path / "photo.json").write_bytes(b"\xff\xd8\xff\xe0 not text")
    msg = fails(["fit", "d", "-o", "o", "--config", str(tmp_path / "photo.json")])
    assert msg.startswith(f"mi-tetvr: cannot read the config {tmp_path / 'photo.json'}")
    msg = fails(["fit", "d", "-o", "o", "--config", str(tmp_path / "none.json")])
    assert "not found" in msg and "none.json" in msg
    msg = fails(["fit", "d", "-o", "o", "--loss", "l1", "--lr-color", "-1"])
    assert msg == "mi-tetvr: lr_color must be >= 0"
    # the penalty's weight: a number or heldout, which needs views to hold out
    capsys.readouterr()
    assert fails(["fit", "d", "-o", "o", "--model", "absorption", "--tv", "auto"]) == 2
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert said.endswith("argument --tv: tv must be a number >= 0 or heldout, got 'auto'")
    msg = fails(["fit", "d", "-o", "o", "--model", "absorption", "--tv", "heldout",
                 "--validation", "0"])
    assert msg.startswith("mi-tetvr:") and "needs validation >= 1" in msg, msg
    assert FitConfig.from_dict(FitConfig(model="absorption", tv="heldout").nested()).solver.tv == \
        "heldout"
    # the adaptive mesh's share of the grid's unknowns: more than the coarse grid's eighth,
    # at most all; an earlier config's switch (true) reads as all of them
    capsys.readouterr()
    assert fails(["fit", "d", "-o", "o", "--model", "absorption", "--adapt", "half"]) == 2
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert said.endswith("argument --adapt: adapt must be a share of the grid's unknowns in "
                         "(0.125, 1], got 'half'")
    for share in ("0.1", "1.5"):
        msg = fails(["fit", "d", "-o", "o", "--model", "absorption", "--adapt", share])
        assert msg.startswith("mi-tetvr: adapt must be a share of the grid's unknowns in "
                              "(0.125, 1]") and share in msg, msg
    assert [FitConfig.from_dict({"solver": {"adapt": v}}).solver.adapt_share
            for v in (None, False, True, 0.5)] == [None, None, 1.0, 0.5]
    # the trilinear basis is the linear solvers' field (on a grid or a graded grid), not an
    # image fit's
    cfg = FitConfig(model="absorption", basis="trilinear", adapt=0.5)
    assert cfg.solver.adapt_share == 0.5
    msg = fails(["fit", "d", "-o", "o", "--basis", "trilinear"])
    assert msg.startswith("mi-tetvr: basis trilinear is the field of model absorption"), msg


def test_config_parts_per_kind_of_fit():
    """Every setting is in one part; each kind of fit's config holds the settings it
    reads (an X-ray fit: the solver, no colors; a color fit: no solver, no transfer
    function), and reads back as the same config."""
    from mi_tetvr.recon.config import KINDS, PARTS
    names = [n for _, (_, part) in PARTS.items() for n in part]
    assert sorted(names) == sorted(f.name for _, f in FitConfig.settings())
    configs = {"color": FitConfig(), "scattering": FitConfig(model="scattering", lights="l.xml"),
               "absorption": FitConfig(model="absorption"),
               "tf": FitConfig(optimize="tf", init="m.vtu"),
               "scalar": FitConfig(optimize="scalar", init="m.vtu", transfer_function="t.json")}
    held = {}
    for kind, cfg in configs.items():
        assert cfg.kind == kind
        nested = cfg.nested()
        held[kind] = {n for part in nested.values() for n in part}
        assert FitConfig.from_dict(nested) == cfg
    assert set(KINDS) == set(held)
    assert "solver" not in configs["color"].nested() and "tv" in held["absorption"]
    assert "lr_color" not in held["absorption"] and "tf_smoothing" not in held["color"]
    assert {"sh_degree", "outer", "appearance"} <= held["color"] - held["scattering"]
    assert {"tf_init", "tf_smoothing"} <= held["tf"] - held["scalar"]
    assert {"transfer_function", "lr_scalar"} <= held["scalar"] - held["tf"]
    assert "lights" in held["scattering"] and "xray_flux" in held["absorption"]


# -- errors, not tracebacks ----------------------------------------------------------------

@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    """A folded mesh with a scalar, one with colors, and a grid mesh with an attenuation."""
    import meshio

    from mi_tetvr.mesh.generate import grid_mesh
    from tests.mesh.test_io import folded_grid
    d = tmp_path_factory.mktemp("meshes")
    v, t = folded_grid()
    meshio.write(d / "folded.vtu", meshio.Mesh(v, [("tetra", t)],
                                               point_data={"density": v[:, 0] + 1.0}))
    meshio.write(d / "folded_colored.vtu", meshio.Mesh(v, [("tetra", t)], point_data={
        "color": np.full((len(v), 3), 0.5), "opacity": np.ones(len(v))}))
    v, t = grid_mesh(2)
    meshio.write(d / "attenuation.vtu", meshio.Mesh(v, [("tetra", t)],
                                                    point_data={"attenuation": v[:, 0] + 1}))
    return d


def test_variant_errors(tmp_path):
    for bad in ("scalar_rgb", "no_such_variant"):
        msg = fails(["make-capture", "-o", str(tmp_path), "--variant", bad])
        assert msg.startswith("mi-tetvr: ") and bad in msg and "llvm_ad_rgb" in msg


def test_missing_and_wrong_files(tmp_path, meshes):
    msg = fails(["eval", str(tmp_path / "missing.vtu"), str(tmp_path), "--variant", VARIANT])
    assert msg == f"mi-tetvr: not found: {tmp_path / 'missing.vtu'}"
    msg = fails(["fit", str(tmp_path), "-o", str(tmp_path / "o"), "--init",
                 str(tmp_path / "missing.vtu")])
    assert "missing.vtu" in msg and "no such mesh file" in msg
    # a data set whose frames list is empty
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "transforms.json").write_text('{"camera_angle_x": 0.7, "frames": []}')
    msg = fails(["fit", str(tmp_path / "empty"), "-o", str(tmp_path / "o"), "--variant",
                 VARIANT])
    assert msg.startswith("mi-tetvr: ") and "no training views" in msg
    # eval of a mesh that holds an attenuation, not colors: refused, pointing to the folder
    (tmp_path / "empty" / "transforms.json").write_text(json.dumps({
        "camera_angle_x": 0.7, "frames": [{"file_path": f"{k}.png", "transform_matrix":
                                           np.eye(4).tolist()} for k in "ab"]}))
    from PIL import Image
    for k in "ab":
        Image.fromarray(np.zeros((4, 4, 4), np.uint8)).save(tmp_path / "empty" / f"{k}.png")
    msg = fails(["eval", str(meshes / "attenuation.vtu"), str(tmp_path / "empty"),
                 "--variant", VARIANT])
    assert "no 'color' and no 'opacity' point array" in msg and "attenuation" in msg
    assert "mi-tetvr eval FIT_DIR DATA" in msg
    msg = fails(["eval", str(tmp_path), str(tmp_path / "empty"), "--variant", VARIANT])
    assert "not a fit's output folder" in msg


def test_folded_meshes_name_the_flag_each_command_has(tmp_path, meshes):
    """make-dataset and fit --init on a mesh that folds over itself: one line naming
    --repair, which both commands have; with it, make-dataset goes on."""
    tf = str(ROOT / "scenes" / "tf_radial.json")
    msg = fails(["make-dataset", str(meshes / "folded.vtu"), "--tf", tf, "-o",
                 str(tmp_path / "d"), "--views", "1", "--test-views", "0", "--res", "4", "-q",
                 "--variant", VARIANT])
    assert "folds over itself" in msg and "--repair" in msg
    cli.main(["make-dataset", str(meshes / "folded.vtu"), "--tf", tf, "-o",
              str(tmp_path / "d"), "--views", "2", "--test-views", "1", "--res", "6x4", "-q",
              "--repair", "--value-range", "0.5,1.5", "--variant", VARIANT])
    info = json.loads((tmp_path / "d" / "volume_info.json").read_text())
    assert info["value_range"] == [0.5, 1.5]
    meta = json.loads((tmp_path / "d" / "transforms_train.json").read_text())
    assert (meta["w"], meta["h"]) == (6, 4) and meta["pixel_sampling"] == "centers"
    msg = fails(["fit", str(tmp_path / "d"), "-o", str(tmp_path / "f"), "--init",
                 str(meshes / "folded.vtu"), "--iterations", "1", "-q", "--variant", VARIANT])
    assert "folds over itself" in msg and "--repair" in msg


@pytest.mark.parametrize("argv", [
    ["make-dataset", "{m}", "--tf", "radial", "--scalar", "density", "-o", "{d}/d",
     "--views", "1", "--test-views", "0", "--res", "4", "-q", "--variant", VARIANT],
    ["render", "{m}", "-o", "{d}/x.png", "--res", "4", "--variant", VARIANT],
    ["render", "{m}", "--tf", "radial", "-o", "{d}/x.png", "--res", "4", "--variant", VARIANT],
    ["fit", "{data}", "-o", "{d}/f", "--init", "{m}", "--iterations", "1", "-q",
     "--variant", VARIANT],
    ["view", "{m}", "--seconds", "0", "--variant", VARIANT],
    ["viewpoint", "{m}", "-o", "{d}/v", "--variant", VARIANT],
    ["eval", "{c}", "{data}", "--variant", VARIANT],
    ["partition", "{m}", "-o", "{d}/p.pvtu", "--blocks", "2"],
    ["refine", "{m}", "--select", "density", "-o", "{d}/r.vtu"],
], ids=lambda argv: " ".join(argv[:1] + [a for a in argv[2:] if a == "--tf"]))
def test_a_folded_mesh_is_one_line_in_every_command(tmp_path, meshes, tiny_data_path, capfd,
                                                   argv):
    """Every command that reads a mesh, given one that folds over itself: the mesh
    is read and its topology built before any plugin sees it, so what is wrong is
    one line (naming --repair), with nothing of Mitsuba's parser and no traceback."""
    argv = [a.format(m=meshes / "folded.vtu", c=meshes / "folded_colored.vtu", d=tmp_path,
                     data=tiny_data_path) for a in argv]
    from mi_tetvr import cli
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    msg = e.value.code
    out, err = capfd.readouterr()
    assert isinstance(msg, str) and msg.startswith("mi-tetvr: ") and "\n" not in msg, msg
    assert "folds over itself" in msg and "--repair" in msg, msg
    for text in (msg, out, err):
        assert "Traceback" not in text and "parser.cpp" not in text, text


def test_a_constant_scalar_and_a_bad_property_are_one_line(tmp_path, capfd):
    """A mesh whose scalar is constant, under a transfer function with no range, and a
    scene whose tetmesh has a property no plugin reads: one line each (Mitsuba's own
    message of two lines joined), no traceback."""
    import meshio

    from mi_tetvr.mesh.generate import grid_mesh
    v, t = grid_mesh(2)
    meshio.write(tmp_path / "flat.vtu", meshio.Mesh(v, [("tetra", t)],
                                                    point_data={"s": np.full(len(v), 2.0)}))
    xml = tmp_path / "bad.xml"
    xml.write_text((ROOT / "scenes" / "default.xml").read_text().replace(
        'value="meshes/blob.vtu"/>', f'value="{ROOT / "scenes" / "meshes" / "blob.vtu"}"/>'
        '<float name="opacity_scal" value="2"/>'))
    flat, out = str(tmp_path / "flat.vtu"), str(tmp_path / "o")
    for argv, said in [
            (["make-dataset", flat, "--tf", "default", "-o", out, "--views", "1",
              "--test-views", "0", "--res", "4", "-q"], "array 's' is constant"),
            (["render", flat, "--tf", "default", "-o", out + ".png", "--res", "4"],
             "the scalar 's' is constant"),
            (["viewpoint", flat, "--tf", "default", "-o", out, "--res", "4"],
             "array 's' is constant"),
            (["render", str(xml), "-o", out + ".png", "--res", "4"],
             'unreferenced property in shape plugin of type "tetmesh": - float "opacity_scal"')]:
        msg = fails(argv + ["--variant", VARIANT])
        err = capfd.readouterr().err
        assert isinstance(msg, str) and "\n" not in msg and said in msg, (argv[0], msg)
        assert "Traceback" not in msg + err, err


def test_make_dataset_refuses_options_that_do_not_apply(tmp_path, meshes):
    vol = tmp_path / "v.npy"
    np.save(vol, np.ones((4, 4, 4), np.float32))
    base = ["make-dataset", str(vol), "-o", str(tmp_path / "x"), "--variant", VARIANT]
    for extra, said in [(["--xray", "--res", "32"], "--res does not apply to X-ray"),
                        (["--xray", "--seed", "2"], "--seed does not apply to X-ray"),
                        (["--xray", "--fov", "30"], "--fov does not apply to a parallel beam"),
                        (["--xray", "--opacity-scale", "2"], "--opacity-scale does not apply"),
                        (["--tf", "t.json", "--beam", "cone"], "--beam does not apply "
                                                               "without --xray"),
                        (["--tf", "t.json", "--scalar", "s"], "--scalar does not apply to a "
                                                              "grid volume")]:
        msg = fails(base + extra)
        assert msg.startswith("mi-tetvr: " + said), (extra, msg)
    msg = fails(["make-dataset", str(meshes / "folded.vtu"), "--tf", "t.json", "--radius", "3",
                 "-o", str(tmp_path / "x")])
    assert "--radius does not apply to a tet mesh" in msg


def test_readme_lists_the_commands_as_the_parsers_have_them():
    """The README's command list is the parsers' (regenerate it with
    ``python -c "from mi_tetvr.cli import command_summary; print(command_summary())"``)."""
    text = (ROOT / "README.md").read_text()
    begin = text.index("<!-- commands:")
    block = text[text.index("\n", begin) + 1:text.index("<!-- /commands -->")].strip()
    assert block == cli.command_summary()


def test_cone_beam_takes_fov_and_radius(tmp_path):
    """make-dataset --xray --beam cone puts its sources at --radius with --fov (they were
    ignored before): the written cameras say so."""
    vol = tmp_path / "v.npy"
    np.save(vol, np.ones((6, 6, 6), np.float32))
    cli.main(["make-dataset", str(vol), "--xray", "--beam", "cone", "--fov", "30",
              "--radius", "5", "--views", "3", "--test-views", "0", "-q", "-o",
              str(tmp_path / "x"), "--variant", VARIANT])
    from mi_tetvr.recon.datasets import load_nerf
    from mi_tetvr.grid.xray import rotation_axis
    from mi_tetvr.grid import load_volume
    views = load_nerf(tmp_path / "x", holdout=None, load_images=False).views
    axis = rotation_axis(load_volume(vol))
    for v in views:
        c = v.camera
        assert np.degrees(2 * np.arctan(c.width / (2 * c.fx))) == pytest.approx(30.0)
        assert np.linalg.norm((c.center - axis)[:2]) == pytest.approx(5.0)


def test_one_module_per_command_and_main_alone_exits():
    """The command line is a package with one module per command (its NAME, HELP,
    add_arguments and run), and only ``main`` ends the process: no other module of it
    calls ``sys.exit`` or raises ``SystemExit``; a command's error is one line."""
    import ast

    package = ROOT / "mi_tetvr" / "cli"
    sub = next(a for a in cli.build_parser()._actions if a.dest == "cmd")
    assert list(sub.choices) == [c.NAME for c in cli.COMMANDS]
    for command in cli.COMMANDS:
        assert command.__file__ == str(package / command.__name__.rsplit(".", 1)[1]) + ".py"
        assert sub.choices[command.NAME].get_default("func") is command.run
    exits = {}
    for path in sorted(package.glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            call = isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr == "exit" and getattr(node.func.value, "id", "") == "sys"
            raised = isinstance(node, ast.Raise) and node.exc is not None and "SystemExit" in \
                ast.unparse(node.exc)
            if call or raised:
                exits.setdefault(path.name, set()).add(
                    next(f.name for f in ast.walk(tree) if isinstance(f, ast.FunctionDef)
                         and f.lineno <= node.lineno <= f.end_lineno))
    assert exits == {"__init__.py": {"main"}}


def test_settings_are_typed_parts():
    """A fit's settings are one dataclass per part: set by name or by part, read by part
    (a setting asked of the whole config says where it is), each part checking its own;
    the same config from its parts, its flat settings (a checkpoint's) and its file."""
    from mi_tetvr.recon.config import MeshSettings, TrainerSettings
    cfg = FitConfig(lr_color=0.3, model="absorption", solver="sart", passes=4)
    assert isinstance(cfg.trainer, TrainerSettings) and cfg.trainer.lr_color == 0.3
    assert cfg.solver.solver == "sart" and cfg.linear_solver == "sart" and cfg.kind == "absorption"
    with pytest.raises(AttributeError, match=r"part 'trainer': config\.trainer\.lr_color"):
        cfg.lr_color
    assert FitConfig(trainer=cfg.trainer, field=cfg.field, solver=cfg.solver) == cfg
    assert FitConfig(**cfg.flat()) == cfg == FitConfig.from_dict(cfg.flat())
    assert cfg.replaced(passes=None).solver.passes is None and cfg.solver.passes == 4
    with pytest.raises(TypeError, match="part 'mesh' is a MeshSettings"):
        FitConfig(mesh=TrainerSettings())
    assert MeshSettings(grid_resolution=8) == FitConfig(grid_resolution=8).mesh
    with pytest.raises(ValueError, match="decay must be in"):
        TrainerSettings(decay=0.0).validate()
    with pytest.raises(ValueError, match="grid_resolution must be >= 1"):
        cfg.updated(grid_resolution=0)
