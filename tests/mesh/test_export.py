"""``mi-tetvr export``: a volume's surface at an opacity level, and its vertices, read
back by a reader the project did not write (trimesh), against the field evaluated here
in float64 (point location by barycentric coordinates in every tet, not VTK's probe that
the export uses to wind its faces)."""
import numpy as np
import pytest

from mi_tetvr import cli
from mi_tetvr.color import srgb_to_linear
from mi_tetvr.mesh.generate import blob_field, grid_mesh
from mi_tetvr.mesh.io import write_tetmesh
from mi_tetvr.mesh.tetmesh import TetMesh

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("pyvista")


def field_at(V, T, values, points):
    """The linear interpolant of ``values`` at ``points``, brute force in float64:
    the barycentric coordinates of each point in every tet, the tet where all are
    >= -1e-9."""
    P = V[T]                                                   # (m, 4, 3)
    A = np.transpose(P[:, 1:] - P[:, :1], (0, 2, 1))           # (m, 3, 3)
    inv = np.linalg.inv(A)
    out = np.full((len(points),) + values.shape[1:], np.nan)
    for k, x in enumerate(points):
        b = np.einsum("mij,mj->mi", inv, x - P[:, 0])
        w = np.concatenate([1 - b.sum(1, keepdims=True), b], 1)
        inside = np.flatnonzero((w >= -1e-9).all(1))
        assert len(inside), x
        t = inside[0]
        out[k] = np.tensordot(w[t], values[T[t]], axes=1)
    return out


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    V, T = grid_mesh(6, jitter=0.1, seed=1)
    C, S = blob_field(V)
    path = tmp_path_factory.mktemp("export") / "blob.vtu"
    write_tetmesh(path, TetMesh(V, T, C, S))
    return path, V, T, C, S


def export(*argv):
    cli.main(["export", *map(str, argv)])


def read_colors(mesh):
    """The linear RGB of 8-bit sRGB vertex colors."""
    return srgb_to_linear(np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0)


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_the_surface_lies_on_the_level_with_the_fields_colors(blob, tmp_path, suffix):
    """Every vertex of the surface is on the level (1e-6 of the opacity's range) and
    carries the field's color there (to 8-bit sRGB rounding); the surface is closed
    and its normals point out of the dense region (positive enclosed volume)."""
    path, V, T, C, S = blob
    out = tmp_path / f"surface{suffix}"
    level = 1.2
    export(path, "-o", out, "--level", level)
    mesh = trimesh.load(out, process=False, force="mesh")
    assert len(mesh.faces) > 100
    P = np.asarray(mesh.vertices, np.float64)
    assert np.abs(field_at(V, T, S, P) - level).max() < 1e-6 * np.ptp(S)
    want = field_at(V, T, C, P)
    # (8-bit sRGB: half a step in sRGB, as linear RGB a little more near 1)
    assert np.abs(read_colors(mesh) - want).max() < 0.6 / 255 * 2.4
    merged = mesh.copy()
    merged.merge_vertices()
    assert merged.is_watertight and merged.volume > 0


def test_the_default_level_and_the_points(blob, tmp_path, capsys):
    """Without --level the surface is at Otsu's threshold of the opacities
    (scikit-image, said in the command's line); --points writes the vertices at or above
    it with their colors."""
    from skimage.filters import threshold_otsu
    path, V, T, C, S = blob
    export(path, "-o", tmp_path / "s.ply")
    level = threshold_otsu(S)
    assert f"opacity {level:g}" in capsys.readouterr().out
    mesh = trimesh.load(tmp_path / "s.ply", process=False)
    assert np.abs(field_at(V, T, S, np.asarray(mesh.vertices)) - level).max() < 1e-5
    export(path, "-o", tmp_path / "p.ply", "--points")
    cloud = trimesh.load(tmp_path / "p.ply", process=False)
    keep = S >= level
    assert len(cloud.vertices) == keep.sum() > 0
    np.testing.assert_allclose(np.asarray(cloud.vertices), V[keep], atol=1e-6)
    got = srgb_to_linear(np.asarray(cloud.colors)[:, :3] / 255.0)
    assert np.abs(got - C[keep]).max() < 0.6 / 255 * 2.4


def test_a_fits_folder_exports_its_fitted_mesh(blob, tmp_path):
    """A fit's folder is read through its config (``mesh.vtu`` of a color fit); a
    transfer-function fit has no volume of its own, and says so."""
    import dataclasses
    import json
    import shutil

    from mi_tetvr.recon.config import FitConfig
    path, V, T, C, S = blob
    fit = tmp_path / "fit"
    fit.mkdir()
    (fit / "config.json").write_text(json.dumps(dataclasses.asdict(FitConfig())))
    shutil.copy(path, fit / "mesh.vtu")
    export(fit, "-o", tmp_path / "fit.ply", "--level", 1.2)
    direct = tmp_path / "direct.ply"
    export(path, "-o", direct, "--level", 1.2)
    a, b = (trimesh.load(f, process=False) for f in (tmp_path / "fit.ply", direct))
    np.testing.assert_array_equal(np.asarray(a.vertices), np.asarray(b.vertices))
    tf_fit = FitConfig(optimize="tf", init="scalar.vtu")
    (fit / "config.json").write_text(json.dumps(dataclasses.asdict(tf_fit)))
    with pytest.raises(SystemExit, match="fitted a transfer function"):
        export(fit, "-o", tmp_path / "tf.ply")


def test_view_dependent_colors_export_their_mean(blob, tmp_path):
    """A mesh of spherical-harmonic colors (a point array ``sh``, no ``color``) exports
    each surface vertex with the colors' mean over the directions: the degree-0 term,
    max(Y_0 k_0 + 0.5, 0) at the vertices, interpolated."""
    path, V, T, C, S = blob
    sh = np.random.default_rng(3).normal(scale=0.8, size=(len(V), 4, 3))
    mean = np.maximum(sh[:, 0] * 0.28209479177387814 + 0.5, 0.0)
    file = tmp_path / "sh.vtu"
    write_tetmesh(file, TetMesh(V, T, None, S, {"sh": sh.reshape(len(V), -1)}))
    export(file, "-o", tmp_path / "sh.ply", "--level", 1.2)
    mesh = trimesh.load(tmp_path / "sh.ply", process=False)
    want = field_at(V, T, mean, np.asarray(mesh.vertices))
    assert np.abs(read_colors(mesh) - np.clip(want, 0, 1)).max() < 0.6 / 255 * 2.4


def test_bad_input_is_one_line_each(blob, tmp_path):
    path, V, T, C, S = blob
    empty = tmp_path / "empty.vtu"
    write_tetmesh(empty, TetMesh(V, T, C, np.zeros(len(V))))
    cases = [((path, "-o", tmp_path / "a.ply", "--level", 100), "no surface at opacity 100"),
             ((empty, "-o", tmp_path / "a.ply"), "an empty volume"),
             ((path, "-o", tmp_path / "a.stl"), "surfaces go to .ply, .obj, .glb"),
             ((path, "-o", tmp_path / "a.glb", "--points"), "point clouds go to .ply, .obj"),
             ((path, "-o", tmp_path / "a.ply", "--array", "color"), "one value per vertex"),
             ((tmp_path / "missing.vtu", "-o", tmp_path / "a.ply"), "not found")]
    for argv, message in cases:
        with pytest.raises(SystemExit) as e:
            export(*argv)
        err = str(e.value.code)       # (main ends the process with the message)
        assert err.startswith("mi-tetvr: ") and message in err and len(err.splitlines()) == 1, \
            err
