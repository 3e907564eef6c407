"""The mi-tetvr command line and the bundled scenes."""
import contextlib
import io
import json
import subprocess
import sys
import warnings

import numpy as np
import pytest

import mitsuba as mi
from tests.helpers import ROOT, VARIANT
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.io import write_tetmesh
from mi_tetvr.mesh.tetmesh import TetMesh
from mi_tetvr.mesh.scenes import make_scenes

SCENES = ["default", "transfer_function", "nonconvex", "two_meshes", "inside", "on_floor",
          "embedded", "two_models", "lit_fog", "lit_field"]


def run(*args):
    """``mi-tetvr ARGS`` from the checkout's root: its exit status and what it printed,
    as ``subprocess.run`` returns them. The command runs in this process (its kernels
    shared with the suite's, no interpreter to start) when the suite's variant is the
    commands' default, with what a process would start from: the working directory,
    Python's default warning filters, Mitsuba's file resolver (restored after);
    else in a process of its own (``test_entry_point_is_a_process`` runs one always)."""
    if VARIANT != "llvm_ad_rgb":
        return process(*args)
    from mi_tetvr import cli
    out, err = io.StringIO(), io.StringIO()
    resolver = [str(p) for p in mi.file_resolver()]
    code = 0
    with contextlib.chdir(ROOT), contextlib.redirect_stdout(out), \
            contextlib.redirect_stderr(err), warnings.catch_warnings():
        warnings.resetwarnings()
        warnings.simplefilter("default")
        warnings.showwarning = warnings._showwarning_orig
        try:
            cli.main([str(a) for a in args])
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
            if isinstance(e.code, str):
                print(e.code, file=err)
    fr = mi.file_resolver()
    fr.clear()
    for path in resolver:
        fr.append(path)
    return subprocess.CompletedProcess(args, code, out.getvalue(), err.getvalue())


def process(*args):
    """``mi-tetvr ARGS`` in a process of its own (``python -m mi_tetvr.cli``)."""
    return subprocess.run([sys.executable, "-m", "mi_tetvr.cli", *args], capture_output=True,
                          text=True, cwd=ROOT)


def test_entry_point_is_a_process(tmp_path):
    """``python -m mi_tetvr.cli`` runs a command, and ends an error with one line and
    status 1 (the other tests run the commands in the suite's process)."""
    r = process("render", "scenes/default.xml", "--res", "8x6", "-o", str(tmp_path / "a.exr"))
    assert r.returncode == 0 and (tmp_path / "a.exr").is_file(), r.stderr
    r = process("render", str(tmp_path / "missing.xml"), "-o", str(tmp_path / "b.exr"))
    assert r.returncode == 1 and r.stderr.strip().count("\n") == 0, r.stderr
    assert r.stderr.startswith("mi-tetvr: ") and "missing.xml" in r.stderr, r.stderr


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    make_scenes(ROOT / "scenes")
    return ROOT / "scenes"


@pytest.mark.parametrize("name", SCENES)
def test_render_scene(scenes, tmp_path, name):
    """``mi-tetvr render`` of each bundled scene writes what Mitsuba renders of that file at
    that film size and sample count: the EXR is ``mi.render``'s RGBA (same seed, so
    equal), the PNG its RGB as 8-bit sRGB (Mitsuba's own conversion, within one level);
    and the volume is in the picture."""
    from mi_tetvr import cli
    exr, png = tmp_path / f"{name}.exr", tmp_path / f"{name}.png"
    cli.main(["render", str(scenes / f"{name}.xml"), "-o", str(exr), "-o", str(png),
              "--res", "24x16", "--spp", "2", "--variant", VARIANT])
    mi.file_resolver().prepend(str(scenes))
    scene = mi.load_string(cli.scene_xml(scenes / f"{name}.xml", (24, 16)))
    ref = np.array(mi.render(scene, spp=2))
    img = np.array(mi.Bitmap(str(exr)))
    assert img.shape == ref.shape == (16, 24, 4)
    np.testing.assert_allclose(img, ref, rtol=1e-6, atol=1e-7)
    assert img[..., 3].max() > 0.05 and np.all((img[..., 3] >= 0) & (img[..., 3] <= 1))
    srgb = np.array(mi.Bitmap(np.ascontiguousarray(ref[..., :3])).convert(
        mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=True))
    written = np.array(mi.Bitmap(str(png))).astype(np.float64) / 255
    assert written.shape == (16, 24, 3)
    assert np.abs(written - np.clip(srgb, 0, 1)).max() <= 1 / 255 + 1e-6


def test_render_errors(scenes, tmp_path):
    r = run("render", "missing.xml", "-o", str(tmp_path / "x.exr"))
    assert r.returncode != 0 and "not found" in r.stderr
    r = run("render", "scenes/default.xml", "-o", str(tmp_path / "x.tif"), "--res", "8x8")
    assert r.returncode != 0 and "unsupported image format" in r.stderr
    # Errors of the scene itself, at load and while rendering: a message, no traceback.
    shape = '<shape type="tetmesh"><string name="filename" value="{}"/>{}</shape>'
    for extra, said in [
            (shape.format(scenes / "meshes" / "blob.vtu", '<emitter type="area"/>'),
             "cannot be an area emitter"),
            (shape.format(scenes / "meshes" / "blob.vtu", "") + shape.format(
                scenes / "meshes" / "radial_scalar.vtu",
                f'<string name="transfer_function" value="{scenes / "tf_radial.json"}"/>'
                '<string name="classification" value="preintegrated"/>'),
             "cannot overlap another tetmesh")]:
        path = tmp_path / "bad.xml"
        path.write_text('<scene version="3.0.0"><integrator type="tetvr"/>'
                        '<sensor type="perspective"><film type="hdrfilm">'
                        '<integer name="width" value="8"/><integer name="height" value="8"/>'
                        f'</film></sensor>{extra}</scene>')
        r = run("render", str(path), "-o", str(tmp_path / "x.exr"))
        assert r.returncode != 0 and said in r.stderr, r.stderr
        assert "Traceback" not in r.stderr


def test_info(tmp_path):
    v, t = grid_mesh(2)
    p = tmp_path / "g.vtu"
    write_tetmesh(p, TetMesh(v, t))
    r = run("info", str(p), "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["tets"] == 48 and s["vertices"] == 27 and s["boundary_faces"] == 48
    assert s["volume"] == pytest.approx(8.0)
    r = run("info", str(tmp_path / "none.vtu"))
    assert r.returncode != 0 and "not found" in r.stderr


def test_make_dataset_fit_eval(tmp_path):
    """The main job end to end on a tiny volume: make-dataset, fit (then a
    resumed fit that has nothing left to do), eval of the written mesh."""
    from mi_tetvr.mesh.scenes import default_volume
    np.save(tmp_path / "vol.npy", default_volume(12))
    data, out = tmp_path / "data", tmp_path / "fit"
    r = run("make-dataset", str(tmp_path / "vol.npy"), "--tf", "scenes/tf_default.json",
            "--views", "4", "--test-views", "2", "--res", "12", "--fov", "30", "--out", str(data))
    assert r.returncode == 0, r.stderr
    r = run("fit", str(data), "--out", str(out), "--grid-resolution", "3", "--iterations", "4",
            "--views-per-step", "2", "--n-sub", "2")
    assert r.returncode == 0, r.stderr
    assert "test PSNR" in r.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["step"] == 4 and len(metrics["views"]) == 2
    r = run("eval", str(out / "mesh.vtu"), str(data), "-o", str(tmp_path / "m.json"))
    assert r.returncode == 0, r.stderr
    assert "mean PSNR" in r.stdout and (tmp_path / "m.json").is_file()
    # the mesh file scores as the fit scored itself (its metrics.json), and so does the folder
    scored = json.loads((tmp_path / "m.json").read_text())["mean"]
    assert scored["psnr"] == pytest.approx(metrics["mean"]["psnr"], abs=1e-4)
    r = run("eval", str(out), str(data), "-o", str(tmp_path / "f.json"))
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "f.json").read_text())["mean"]["psnr"] == \
        pytest.approx(metrics["mean"]["psnr"], abs=1e-4)
    # resuming into the folder with other settings is refused, naming them and the way out
    r = run("fit", str(data), "--out", str(out), "--grid-resolution", "3", "--iterations", "4",
            "--views-per-step", "2", "--n-sub", "2", "--model", "absorption")
    assert r.returncode == 1 and "model: \"emission\" there, \"absorption\" now" in r.stderr
    assert "--restart" in r.stderr and "Traceback" not in r.stderr
    # Bad input: a clear message, no traceback.
    r = run("fit", str(tmp_path / "nowhere"), "--out", str(out))
    assert r.returncode != 0 and "not found" in r.stderr and "Traceback" not in r.stderr
    r = run("fit", str(data), "--out", str(out), "--background", "purple")
    assert r.returncode != 0 and "--background" in r.stderr


def test_transfer_function_and_xray_commands(tmp_path):
    """The visualization and tomography jobs end to end, tiny: make-dataset of
    a scalar mesh, fit --optimize tf writing transfer_function.json (the
    texels as control points); make-dataset --xray, fit --model absorption
    writing an 'attenuation' mesh; clear errors for wrong combinations."""
    make_scenes(ROOT / "scenes")
    mesh = str(ROOT / "scenes" / "meshes" / "radial_scalar.vtu")
    data, out = tmp_path / "data", tmp_path / "tf"
    r = run("make-dataset", mesh, "--tf", "scenes/tf_radial.json", "--views", "3",
            "--test-views", "1", "--res", "12", "--out", str(data))
    assert r.returncode == 0, r.stderr
    assert json.loads((data / "volume_info.json").read_text())["scalar"] == "density"
    r = run("fit", str(data), "--init", mesh, "--optimize", "tf", "--tf-resolution", "8",
            "--iterations", "3", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "transfer_function.json" in r.stdout
    tf = json.loads((out / "transfer_function.json").read_text())
    assert len(tf["opacity"]) == 8 and tf["opacity"][0][0] == pytest.approx(1 / 16)
    r = run("fit", str(data), "--optimize", "tf", "--out", str(out))      # no scalar mesh
    assert r.returncode != 0 and "scalar mesh as init" in r.stderr
    from mi_tetvr.mesh.scenes import default_volume
    np.save(tmp_path / "vol.npy", default_volume(8))
    xray, fit = tmp_path / "xray", tmp_path / "att"
    r = run("make-dataset", str(tmp_path / "vol.npy"), "--xray", "--views", "6",
            "--test-views", "2", "--out", str(xray))
    assert r.returncode == 0, r.stderr
    assert len(list((xray / "train").glob("*.npy"))) == 6
    # Poisson counts of a finer field: recorded, and the counts are multiples of 1 / flux
    noisy = tmp_path / "noisy"
    r = run("make-dataset", str(tmp_path / "vol.npy"), "--xray", "--views", "6",
            "--test-views", "2", "--flux", "500", "--detail", "2", "--out", str(noisy))
    assert r.returncode == 0, r.stderr
    assert "500 photons" in r.stdout
    info = json.loads((noisy / "xray_info.json").read_text())
    assert info["xray_flux"] == 500 and info["detail"] == 2
    counts = 500 * np.load(noisy / "train" / "p_000.npy")           # transmittance
    assert np.allclose(counts, np.round(counts), atol=1e-3) and counts.max() > 100
    r = run("make-dataset", str(tmp_path / "vol.npy"), "--xray", "--detail", "0",
            "--out", str(noisy))
    assert r.returncode == 1 and "--detail must be a positive integer" in r.stderr
    # a limited-angle scan: the cameras' own view directions (not the angles it records)
    # span 90 degrees in even steps of 90 / 6, the held-out ones between them
    limited = tmp_path / "limited"
    r = run("make-dataset", str(tmp_path / "vol.npy"), "--xray", "--views", "6",
            "--test-views", "2", "--arc", "90", "--out", str(limited))
    assert r.returncode == 0 and "over 90 degrees" in r.stdout, r.stderr

    def directions(split):
        frames = json.loads((limited / f"transforms_{split}.json").read_text())["frames"]
        fwd = -np.array([f["transform_matrix"] for f in frames])[:, :3, 2]   # looks down -z
        return np.degrees(np.unwrap(np.arctan2(fwd[:, 1], fwd[:, 0])))
    train, test = directions("train"), directions("test")
    assert np.allclose(np.diff(train), np.diff(train)[0]) and \
        abs(abs(train[-1] - train[0]) - 75.0) < 1e-6
    assert np.all((test - train.min()) * (train.max() - test) > 0)   # inside the arc
    for bad in ("200", "0"):
        r = run("make-dataset", str(tmp_path / "vol.npy"), "--xray", "--arc", bad,
                "--out", str(tmp_path / "bad"))
        assert r.returncode == 1 and "arc must lie in (0, 180]" in r.stderr
    r = run("fit", str(xray), "--model", "absorption", "--grid-resolution", "4", "--iterations",
            "3", "--out", str(fit))
    assert r.returncode == 0, r.stderr
    assert "(transmittance)" in r.stdout
    # eval scores what was fitted: the attenuation's transmittance, as the fit did; its
    # mesh alone (no colors) is refused with the way to score it
    r = run("eval", str(fit), str(xray), "-o", str(tmp_path / "att.json"))
    assert r.returncode == 0, r.stderr
    assert "(transmittance)" in r.stdout
    fitted = json.loads((fit / "metrics.json").read_text())["mean"]["psnr"]
    assert json.loads((tmp_path / "att.json").read_text())["mean"]["psnr"] == \
        pytest.approx(fitted, abs=1e-4)
    r = run("eval", str(fit / "attenuation.vtu"), str(xray))
    assert r.returncode == 1 and "mi-tetvr eval FIT_DIR DATA" in r.stderr
    import meshio
    assert "attenuation" in meshio.read(fit / "attenuation.vtu").point_data
    r = run("make-dataset", str(tmp_path / "vol.npy"), "--out", str(tmp_path / "x"))
    assert r.returncode != 0 and "--tf" in r.stderr


def test_refine_command(tmp_path):
    V, T = grid_mesh(3, jitter=0.1, seed=2)
    score = np.zeros(len(V))
    score[[5, 20]] = 1.0
    src = tmp_path / "m.vtu"
    write_tetmesh(src, TetMesh(V, T, point_data={"score": score}))
    r = run("refine", str(src), "--select", "score", "--fraction", "0.05", "-o",
            str(tmp_path / "r.vtu"))
    assert r.returncode == 0, r.stderr
    from mi_tetvr.mesh.io import read_tetmesh
    out = read_tetmesh(tmp_path / "r.vtu")
    assert len(out.tets) > len(T) and len(out.vertices) > len(V)
    r = run("refine", str(src), "--select", "nope", "-o", str(tmp_path / "x.vtu"))
    assert r.returncode != 0 and "nope" in r.stderr and "Traceback" not in r.stderr


def test_info_reports_problems_arrays_and_always_prints_json(tmp_path):
    import meshio
    from tests.mesh.test_io import folded_grid
    v, t = folded_grid()
    p = tmp_path / "folded.vtu"
    meshio.write(p, meshio.Mesh(v, [("tetra", t)], cell_data={"stress": [np.arange(len(t))]}))
    r = run("info", str(p), "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert "folds over itself" in s["problems"][0] and "--repair" in s["problems"][0]
    assert s["repair"]["folded"] == 2 and s["repair"]["drops"] == 2
    r = run("info", str(p), "--repair", "--cell-to-point", "--json")
    s = json.loads(r.stdout)
    assert s["tets"] == len(t) - 2 and "repair dropped 2" in s["warnings"][0]
    assert s["arrays"]["stress"]["kind"] == "point"
    r = run("info", str(p), "--repair")
    assert r.returncode == 0 and "cell array 'stress'" in r.stdout
    r = run("info", str(tmp_path / "none.vtu"), "--json")
    assert r.returncode == 1 and "not found" in json.loads(r.stdout)["error"]


def test_render_res_on_a_fixed_film_and_repair(tmp_path):
    """--res on a scene whose film has literal sizes; a folded mesh is refused
    with the flag that loads it, and renders with that flag."""
    import meshio
    from tests.mesh.test_io import folded_grid
    v, t = folded_grid()
    meshio.write(tmp_path / "folded.vtu", meshio.Mesh(v, [("tetra", t)]))
    text = (ROOT / "scenes" / "default.xml").read_text()
    text = text.replace("$resx", "64").replace("$resy", "48")
    text = text.replace("meshes/blob.vtu", "folded.vtu")
    (tmp_path / "scene.xml").write_text(text)
    out = tmp_path / "x.exr"
    r = run("render", str(tmp_path / "scene.xml"), "-o", str(out), "--res", "24x16", "--spp", "1")
    assert r.returncode != 0 and "--repair" in r.stderr and "Traceback" not in r.stderr
    r = run("render", str(tmp_path / "scene.xml"), "-o", str(out), "--res", "24x16", "--spp",
            "1", "--repair")
    assert r.returncode == 0, r.stderr
    assert np.array(mi.Bitmap(str(out))).shape == (16, 24, 4)


def test_render_shaded(tmp_path):
    """--shade lights the volume (the colors change, the coverage does not);
    it needs --tf and volume rendering."""
    from mi_tetvr.recon.images import read_image
    make_scenes(ROOT / "scenes")
    mesh = str(ROOT / "scenes" / "meshes" / "radial_scalar.vtu")
    images = []
    for extra in ([], ["--shade"]):
        out = tmp_path / f"shade{len(extra)}.exr"
        r = run("render", mesh, "--tf", "scenes/tf_radial.json", "--res", "24x16", "-o",
                str(out), *extra)
        assert r.returncode == 0, r.stderr
        images.append(read_image(out))
    np.testing.assert_allclose(images[0][..., 3], images[1][..., 3], atol=1e-6)
    assert np.abs(images[0][..., :3] - images[1][..., :3]).max() > 0.02
    for flags, said in ((["--shade"], "--shade needs --tf"),
                        (["--shade", "--mode", "max"], "--shade lights volume rendering")):
        r = run("render", mesh, "-o", str(tmp_path / "x.png"), *flags)
        assert r.returncode != 0 and said in r.stderr, r.stderr


def test_render_cell_data(tmp_path):
    """render MESH --scalar NAME of a cell array renders it constant in each
    tet (not the image of the array averaged onto the vertices, which
    --cell-to-point asks for); the projections say they show point data."""
    from mi_tetvr.recon.images import read_image
    V, T = grid_mesh(3, jitter=0.1, seed=2)
    values = np.random.default_rng(0).uniform(size=len(T))
    path = tmp_path / "cells.vtu"
    write_tetmesh(path, TetMesh(V, T, cell_data={"p": values}), color=None, opacity=None)
    images = {}
    for name, extra in (("cells", []), ("points", ["--cell-to-point"])):
        out = tmp_path / f"{name}.exr"
        r = run("render", str(path), "--scalar", "p", "--tf", "viridis", "--res", "16x16",
                "-o", str(out), *extra)
        assert r.returncode == 0, r.stderr
        images[name] = read_image(out)
    assert images["cells"][..., 3].max() > 0.1
    assert np.abs(images["cells"] - images["points"]).max() > 0.05
    r = run("render", str(path), "--scalar", "p", "--mode", "max", "-o",
            str(tmp_path / "max.exr"))
    assert r.returncode != 0 and "--mode max shows point data" in r.stderr, r.stderr


def test_render_a_mesh_file(tmp_path):
    """render MESH frames a mesh file without XML: volume rendering or the
    intensity projections of its scalar (through gray, a monotone map: per
    pixel min <= mean <= max, and the mesh's coverage the same in all three);
    the mesh-only flags are refused for an XML scene, --mode too."""
    from mi_tetvr.recon.images import read_image
    make_scenes(ROOT / "scenes")
    mesh = str(ROOT / "scenes" / "meshes" / "radial_scalar.vtu")
    images = {}
    for mode in ("max", "mean", "min", "dvr"):
        out = tmp_path / f"{mode}.exr"
        extra = ["--tf", "scenes/tf_radial.json"] if mode == "dvr" else []
        r = run("render", mesh, "--mode", mode, "--res", "24x16", "--view", "30,20",
                "-o", str(out), *extra)
        assert r.returncode == 0, r.stderr
        images[mode] = read_image(out)
    assert images["max"].shape == (16, 24, 4)
    met = images["max"][..., 3] > 0
    assert 0 < met.sum() < met.size
    for mode in ("mean", "min"):
        np.testing.assert_array_equal(images[mode][..., 3] > 0, met)
    lo, mid, hi = (images[m][..., 0][met] for m in ("min", "mean", "max"))
    assert np.all(lo <= mid + 1e-6) and np.all(mid <= hi + 1e-6) and np.any(lo < hi - 1e-3)
    assert images["dvr"][..., 3].max() > 0
    # a slice through the centre shows inside the projection's coverage, not all of it
    r = run("render", mesh, "--mode", "slice", "--res", "24x16", "--view", "30,20",
            "-o", str(tmp_path / "slice.exr"))
    assert r.returncode == 0, r.stderr
    cut = read_image(tmp_path / "slice.exr")[..., 3] > 0
    assert cut.any() and not np.any(cut & ~met)
    # an isosurface at the middle of the range: inside the projection's coverage
    import mi_tetvr
    values = next(iter(mi_tetvr.read_tetmesh(mesh).point_data.values()))
    middle = (float(np.min(values)) + float(np.max(values))) / 2
    r = run("render", mesh, "--mode", "iso", "--iso", str(middle), "--res", "24x16",
            "--view", "30,20", "-o", str(tmp_path / "iso.exr"))
    assert r.returncode == 0, r.stderr
    iso = read_image(tmp_path / "iso.exr")[..., 3] > 0
    assert iso.any() and not np.any(iso & ~met)
    # the isosurface drawn in the volume: where it is met, the volume in
    # front of it and the surface replace what lay behind; elsewhere the
    # volume alone, unchanged
    r = run("render", mesh, "--tf", "scenes/tf_radial.json", "--iso", str(middle),
            "--res", "24x16", "--view", "30,20", "-o", str(tmp_path / "dvr_iso.exr"))
    assert r.returncode == 0, r.stderr
    both = read_image(tmp_path / "dvr_iso.exr")
    changed = np.abs(both - images["dvr"]).max(-1) > 1e-6
    assert changed.any() and np.array_equal(changed, iso)
    assert np.all(both[..., 3][iso] > 0.999)
    # translucent: between the volume alone and the opaque surface
    r = run("render", mesh, "--tf", "scenes/tf_radial.json", "--iso", str(middle),
            "--surface-opacity", "0.5", "--res", "24x16", "--view", "30,20",
            "-o", str(tmp_path / "dvr_iso_half.exr"))
    assert r.returncode == 0, r.stderr
    half = read_image(tmp_path / "dvr_iso_half.exr")
    assert np.array_equal(np.abs(half - images["dvr"]).max(-1) > 1e-6, iso)
    for flags, said in ((["--iso", "0.5", "--plane", "0,0,0,0,0,1"], "one kind of surface"),
                        (["--surface-opacity", "0.5"], "--surface-opacity is an opacity"),
                        (["--iso", "0.5", "--surface-opacity", "1.5"], "an opacity in (0, 1]")):
        r = run("render", mesh, "--tf", "scenes/tf_radial.json", "-o", str(tmp_path / "x.png"),
                *flags)
        assert r.returncode != 0 and said in r.stderr, r.stderr
    # clipped away on one side of a plane: less of the mesh, nothing new
    r = run("render", mesh, "--mode", "max", "--res", "24x16", "--view", "30,20",
            "--clip", "0,0,0,1,0,0", "-o", str(tmp_path / "clip.exr"))
    assert r.returncode == 0, r.stderr
    kept = read_image(tmp_path / "clip.exr")[..., 3] > 0
    assert 0 < kept.sum() < met.sum() and not np.any(kept & ~met)
    scene = str(ROOT / "scenes" / "default.xml")
    for flags, said in ((["--mode", "max"], "--mode applies to a mesh file"),
                        (["--view", "10,10"], "--view frames a mesh file"),
                        (["--tf", "viridis"], "--tf does not apply to an XML scene"),
                        (["--plane", "0,0,0,0,0,1"], "--plane does not apply"),
                        (["--clip", "0,0,0,0,0,1"], "--clip does not apply"),
                        (["--iso", "0.5"], "--iso does not apply")):
        r = run("render", scene, "-o", str(tmp_path / "x.png"), *flags)
        assert r.returncode != 0 and said in r.stderr, r.stderr
    r = run("render", mesh, "--view", "10", "-o", str(tmp_path / "x.png"))
    assert r.returncode == 2 and "expected 2 comma-separated numbers" in r.stderr


def test_render_an_orbit(tmp_path):
    """render MESH --orbit N: N frames once around --up, as an MP4 (read back:
    N frames of the film's size) and a contact sheet of the frames; the first
    and the last frame (whose kernels the orbit replays) are what render MESH
    writes at their views."""
    import imageio_ffmpeg
    from mi_tetvr.recon.images import read_image
    make_scenes(ROOT / "scenes")
    mesh = str(ROOT / "scenes" / "meshes" / "radial_scalar.vtu")
    video, sheet = tmp_path / "orbit.mp4", tmp_path / "orbit.png"
    r = run("render", mesh, "--mode", "max", "--res", "16x12", "--orbit", "4", "-o", str(video),
            "-o", str(sheet), "-o", str(tmp_path / "orbit.exr"))
    assert r.returncode == 0, r.stderr
    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    assert tuple(meta["size"]) == (16, 12) and len(list(reader)) == 4
    assert read_image(sheet).shape[:2] == (2 * 12 + 2, 2 * 16 + 2)
    r = run("render", mesh, "--mode", "max", "--res", "16x12", "-o", str(tmp_path / "one.png"))
    assert r.returncode == 0, r.stderr
    first = read_image(tmp_path / "one.png")[..., :3]
    np.testing.assert_allclose(read_image(sheet)[:12, :16, :3], first, atol=1e-6)
    # the fourth frame: 270 degrees on from the default view (45, 30)
    r = run("render", mesh, "--mode", "max", "--res", "16x12", "--view", "315,30", "-o",
            str(tmp_path / "last.exr"))
    assert r.returncode == 0, r.stderr
    last = read_image(tmp_path / "last.exr")[..., :3]
    assert np.abs(last - first).max() > 0.05
    np.testing.assert_allclose(read_image(tmp_path / "orbit.exr")[14:26, 18:34, :3], last,
                               atol=1e-6)
    r = run("render", mesh, "--orbit", "4", "-o", str(tmp_path / "x.exr"))
    assert r.returncode != 0 and ".mp4" in r.stderr


def test_render_a_time_series(tmp_path):
    """Several mesh files (or a .pvd of them) render with one camera and one
    transfer function range: a field that grows from file to file grows from
    frame to frame (each file's own range would make the frames alike); the
    .pvd's time steps, not its listing order, order the frames."""
    import imageio_ffmpeg
    from mi_tetvr.recon.images import read_image
    v, t = grid_mesh(3, jitter=0.1)
    base = 0.2 + 0.8 * np.exp(-np.sum(v ** 2, 1))
    names = []
    for k in range(3):
        name = tmp_path / f"step{k}.vtu"
        write_tetmesh(name, TetMesh(v, t, point_data={"s": base * (k + 1)}))
        names.append(str(name))
    r = run("render", *names, "--scalar", "s", "--mode", "max", "--res", "12",
            "-o", str(tmp_path / "s.mp4"),
            "-o", str(tmp_path / "f.exr"))
    assert r.returncode == 0, r.stderr
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "s.mp4"))
    next(reader)
    assert len(list(reader)) == 3
    levels = [read_image(tmp_path / f"f_{k:04d}.exr")[..., :3].max() for k in range(3)]
    assert levels[0] < levels[1] < levels[2], levels
    (tmp_path / "series.pvd").write_text(
        '<VTKFile type="Collection"><Collection>'
        + "".join(f'<DataSet timestep="{k}" file="step{k}.vtu"/>' for k in (2, 0, 1))
        + "</Collection></VTKFile>")
    r = run("render", str(tmp_path / "series.pvd"), "--scalar", "s", "--mode", "max", "--res",
            "12",
            "-o", str(tmp_path / "p.exr"))
    assert r.returncode == 0, r.stderr
    for k in range(3):
        np.testing.assert_array_equal(read_image(tmp_path / f"p_{k:04d}.exr"),
                                      read_image(tmp_path / f"f_{k:04d}.exr"))
    r = run("render", names[0], str(ROOT / "scenes" / "default.xml"), "-o",
            str(tmp_path / "x.png"))
    assert r.returncode == 1 and "render takes a Mitsuba XML scene, or tet mesh files" in r.stderr
