"""``render MESH --lights XML``: a scalar mesh lit by a scene's emitters
(:mod:`mi_tetvr.apps.lit`). Its surfaces are VTK's contour and cut: the
isosurface's vertices carry the isovalue and the slice's lie in its plane,
colored by the transfer function; the renders are finite and lit; the
options that do not combine are refused."""
import numpy as np
import pytest

import mitsuba as mi

from mi_tetvr.apps.lit import surface_meshes
from mi_tetvr.mesh.io import read_tetmesh
from mi_tetvr.mesh.sample import sample_field
from mi_tetvr.transfer import read_transfer_function
from tests.helpers import ROOT, VARIANT

MESH = ROOT / "scenes" / "meshes" / "radial_scalar.vtu"
TF = ROOT / "scenes" / "tf_radial.json"
LIGHTS = ROOT / "scenes" / "lights_sun.xml"


@pytest.fixture(scope="module")
def mesh():
    return read_tetmesh(MESH, color=None, opacity=None)


def test_surfaces_are_the_contour_and_the_cut(mesh):
    tf = read_transfer_function(TF)
    s = np.asarray(mesh.point_data["density"], np.float64)
    lo, hi = float(s.min()), float(s.max())
    iso = surface_meshes(mesh, "density", tf, (lo, hi), "iso", iso=(0.3, 0.6))
    for name, v in zip(sorted(iso), (0.3, 0.6)):
        p = np.array(mi.traverse(iso[name])["vertex_positions"]).reshape(-1, 3)
        assert len(p) > 10
        np.testing.assert_allclose(sample_field(mesh.vertices, mesh.tets, s, p), v, atol=1e-4)
    plane = (0.1, 0.0, 0.0, 1.0, 0.0, 0.0)
    cut = surface_meshes(mesh, "density", tf, (lo, hi), "slice", plane=plane)["slice"]
    p = np.array(mi.traverse(cut)["vertex_positions"]).reshape(-1, 3)
    np.testing.assert_allclose(p[:, 0], 0.1, atol=1e-5)
    color = np.array(cut.attribute_buffer("vertex_color")).reshape(-1, 3)
    expected, _ = tf.shade(sample_field(mesh.vertices, mesh.tets, s, p), (lo, hi))
    np.testing.assert_allclose(color, np.clip(expected, 0, 1), atol=2e-3)
    with pytest.raises(ValueError, match="no isosurface"):
        surface_meshes(mesh, "density", tf, (lo, hi), "iso", iso=(5.0,))


@pytest.mark.parametrize("mode", [["--mode", "iso", "--iso", "0.5"], ["--mode", "slice"],
                                  ["--mode", "dvr", "--iso", "0.7"]])
def test_lit_renders(tmp_path, mode):
    """Finite, lit (brighter than the sky alone) and the volume or its
    surfaces in the picture."""
    from mi_tetvr import cli
    exr = tmp_path / "lit.exr"
    cli.main(["render", str(MESH), "--tf", str(TF), "--lights", str(LIGHTS), *mode, "--res",
              "32x24", "--spp", "16", "-o", str(exr), "--variant", VARIANT])
    img = np.array(mi.Bitmap(str(exr)))[..., :3]
    assert np.all(np.isfinite(img))
    sky = np.median(img.reshape(-1, 3), axis=0)
    assert (img.sum(-1) > sky.sum() * 1.5).sum() >= 3


def test_lit_refusals():
    from mi_tetvr.apps.settings import RenderSettings
    for kwargs, message in [({"mode": "max"}, "--lights path traces"),
                            ({"mode": "dvr"}, "--lights path traces"),
                            ({"mode": "iso", "shade": True}, "does not combine with --shade")]:
        with pytest.raises(ValueError, match=message):
            RenderSettings(lights="x.xml", **kwargs).validate("mesh")
    with pytest.raises(ValueError, match="own emitters"):
        RenderSettings(lights="x.xml", mode="iso").validate("xml")
