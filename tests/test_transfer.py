"""Tests for mi_tetvr.transfer (fast, CPU only)."""

import json
import warnings

import numpy as np
import pytest

from mi_tetvr.transfer import (TransferFunction, read_difftetvr_xml, read_json,
                               read_transfer_function, write_json)
from mi_tetvr.color import srgb_to_linear
from tests.helpers import DATA, shared_data

TF_DIR = DATA / "transfer-functions" / "difftetvr"
DIFFTETVR_XMLS = ["Grey.xml", "Tooth1.xml", "Tooth3Gauss.xml", "Tooth3Linear.xml"]


def _need_data():
    shared_data("transfer-functions", "difftetvr")


def _simple_tf():
    # color: red at 0, green at 0.5, blue at 1; opacity: 0 at 0.2, 1 at 0.6
    return TransferFunction(
        [0.0, 0.5, 1.0],
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [0.2, 0.6],
        [0.0, 1.0],
    )


# ---------------------------------------------------------------- sRGB
def test_srgb_to_linear_known_values():
    got = srgb_to_linear([0.0, 1.0, 0.5, 0.04045, 0.02])
    want = [0.0, 1.0, 0.21404114, 0.04045 / 12.92, 0.02 / 12.92]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-8)
    assert got.dtype == np.float64


def test_srgb_to_linear_shape_and_continuity():
    c = np.linspace(0, 1, 12).reshape(3, 4)
    assert srgb_to_linear(c).shape == (3, 4)
    eps = 1e-12
    lo, hi = srgb_to_linear([0.04045 - eps, 0.04045 + eps])
    assert abs(hi - lo) < 1e-8
    assert np.all(np.diff(srgb_to_linear(np.linspace(0, 1, 1001))) > 0)


# ---------------------------------------------------------- evaluation
def test_eval_at_control_points_and_midpoints():
    tf = _simple_tf()
    color, opacity = tf(np.array([0.0, 0.25, 0.5, 0.75, 1.0]))
    assert color.shape == (5, 3) and opacity.shape == (5,)
    assert color.dtype == np.float64 and opacity.dtype == np.float64
    np.testing.assert_allclose(
        color,
        [[1, 0, 0], [0.5, 0.5, 0], [0, 1, 0], [0, 0.5, 0.5], [0, 0, 1]],
        atol=1e-15,
    )
    # opacity: 0 up to 0.2, linear to 1 at 0.6, then 1
    np.testing.assert_allclose(opacity, [0.0, 0.125, 0.75, 1.0, 1.0], atol=1e-15)
    _, o = tf([0.2, 0.4, 0.6])
    np.testing.assert_allclose(o, [0.0, 0.5, 1.0], atol=1e-15)


def test_clamping_outside_unit_interval():
    tf = _simple_tf()
    color, opacity = tf([-3.0, -1e-9, 1.0 + 1e-9, 7.0])
    np.testing.assert_allclose(color, [[1, 0, 0], [1, 0, 0], [0, 0, 1], [0, 0, 1]])
    np.testing.assert_allclose(opacity, [0.0, 0.0, 1.0, 1.0])


def test_jump_with_duplicate_positions():
    tf = TransferFunction([0, 1], [[0, 0, 0], [1, 1, 1]], [0, 0.5, 0.5, 1], [0, 0, 1, 1])
    _, o = tf([0.49, 0.5, 0.51])
    np.testing.assert_allclose(o, [0.0, 1.0, 1.0])


def test_single_control_point_is_constant():
    tf = TransferFunction([0.3], [[0.1, 0.2, 0.3]], [0.7], [0.4])
    c, o = tf([0.0, 0.5, 1.0])
    np.testing.assert_allclose(c, [[0.1, 0.2, 0.3]] * 3)
    np.testing.assert_allclose(o, [0.4] * 3)


def test_call_nan_raises():
    with pytest.raises(ValueError, match="NaN"):
        _simple_tf()([0.1, np.nan])


def test_shade_default_range_and_scale():
    tf = _simple_tf()
    s = np.array([10.0, 15.0, 20.0])
    color, opacity = tf.shade(s, opacity_scale=4.0)
    c_ref, o_ref = tf([0.0, 0.5, 1.0])
    np.testing.assert_allclose(color, c_ref)
    np.testing.assert_allclose(opacity, 4.0 * o_ref)


def test_shade_explicit_range_clamps():
    tf = _simple_tf()
    color, opacity = tf.shade([0.0, 5.0, 10.0, 20.0], value_range=(0.0, 10.0))
    c_ref, o_ref = tf([0.0, 0.5, 1.0, 1.0])
    np.testing.assert_allclose(color, c_ref)
    np.testing.assert_allclose(opacity, o_ref)


def test_shade_constant_field_maps_to_zero():
    tf = _simple_tf()
    color, opacity = tf.shade(np.full(4, 3.5))
    c0, o0 = tf([0.0])
    np.testing.assert_allclose(color, np.repeat(c0, 4, axis=0))
    np.testing.assert_allclose(opacity, np.repeat(o0, 4))


def test_shade_bad_input():
    tf = _simple_tf()
    with pytest.raises(ValueError, match="NaN"):
        tf.shade([1.0, np.nan, 2.0])
    with pytest.raises(ValueError, match="lo <= hi"):
        tf.shade([1.0, 2.0], value_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="opacity_scale"):
        tf.shade([1.0, 2.0], opacity_scale=-1.0)


# ------------------------------------------------------------ validation
@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(color_positions=[0.0, 0.6, 0.5]), "non-decreasing"),
        (dict(opacity_positions=[1.0, 0.0]), "non-decreasing"),
        (dict(opacities=[0.5, -0.1]), "opacities must be >= 0"),
        (dict(opacities=[0.5, np.nan]), "non-finite"),
        (dict(color_positions=[0.0, np.nan, 1.0]), "non-finite"),
        (dict(colors=[[1, 0, 0], [0, np.nan, 0], [0, 0, 1]]), "non-finite"),
        (dict(colors=[[1, 0], [0, 1], [0, 0]]), r"shape \(p, 3\)"),
        (dict(colors=[[1, 0, 0], [0, 1, 0]]), "rows"),
        (dict(opacities=[0.0, 0.5, 1.0]), "opacities has 3 entries"),
        (dict(color_positions=[[0.0, 0.5, 1.0]]), "1D"),
        (dict(opacity_positions=[], opacities=[]), "at least one"),
        (dict(color_positions=[0.0, 0.5, 1.5]), r"in \[0, 1\]"),
        (dict(colors=[[1, 0, 0], [0, -1, 0], [0, 0, 1]]), "colors must be >= 0"),
    ],
)
def test_bad_constructor_input(kwargs, match):
    args = dict(
        color_positions=[0.0, 0.5, 1.0],
        colors=[[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        opacity_positions=[0.0, 1.0],
        opacities=[0.0, 1.0],
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        TransferFunction(**args)


def test_arrays_are_readonly_copies():
    pos = np.array([0.0, 1.0])
    tf = TransferFunction(pos, [[0, 0, 0], [1, 1, 1]], [0.0], [1.0])
    pos[0] = 0.5
    assert tf.color_positions[0] == 0.0
    with pytest.raises(ValueError):
        tf.colors[0, 0] = 1.0


def test_unknown_suffix(tmp_path):
    p = tmp_path / "tf.txt"
    p.write_text("x")
    with pytest.raises(ValueError, match="unknown transfer function file suffix"):
        read_transfer_function(p)


# ------------------------------------------------------------------ XML
def test_grey_xml():
    _need_data()
    tf = read_transfer_function(TF_DIR / "Grey.xml")
    c, o = tf([0.0, 1.0])
    np.testing.assert_allclose(c[0], [srgb_to_linear(53853 / 65535)] * 3, rtol=1e-12)
    np.testing.assert_allclose(c[1], [srgb_to_linear(49151 / 65535)] * 3, rtol=1e-12)
    np.testing.assert_allclose(o, [1.0, 1.0])


@pytest.mark.parametrize("name", DIFFTETVR_XMLS)
def test_all_difftetvr_xmls_load(name):
    _need_data()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # all ship interpolation_colorspace="Linear RGB"
        tf = read_difftetvr_xml(TF_DIR / name)
    assert tf.colors.shape[1] == 3
    assert tf.colors.shape[0] == tf.color_positions.shape[0] >= 2
    assert tf.opacities.shape == tf.opacity_positions.shape
    c, o = tf(np.linspace(0, 1, 17))
    assert np.all(np.isfinite(c)) and np.all(c >= 0) and np.all(c <= 1)
    assert np.all(o >= 0) and np.all(o <= 1)


def test_tooth3linear_values():
    _need_data()
    tf = read_difftetvr_xml(TF_DIR / "Tooth3Linear.xml")
    c, o = tf([1.0, 0.3])
    np.testing.assert_allclose(o, [0.7300000190734863, 0.0])
    want = srgb_to_linear([0.9999960064888, 0.9999998807907104, 0.999989926815033])
    np.testing.assert_allclose(c[0], want, rtol=1e-12)
    np.testing.assert_allclose(c[1], [0, 0, 0])


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_xml_color_data_modes_and_linear_colorspace(tmp_path):
    body = (
        '<TransferFunction colorspace="{cs}" interpolation_colorspace="Linear RGB">'
        '<OpacityPoints><OpacityPoint position="0" opacity="0.5"/></OpacityPoints>'
        '<ColorPoints {cd}><ColorPoint position="0" r="{v}" g="0" b="0"/></ColorPoints>'
        "</TransferFunction>"
    )
    cases = [
        ("Linear RGB", 'color_data="ushort"', "65535", 1.0),
        ("Linear RGB", 'color_data="float"', "0.25", 0.25),
        ("Linear RGB", 'color_data="float_255"', "51", 0.2),
        ("Linear RGB", "", "51", 0.2),  # sgl default: ubyte
        ("sRGB", 'color_data="ubyte"', "255", 1.0),
        ("sRGB", 'color_data="float"', "0.5", 0.21404114),
    ]
    for i, (cs, cd, v, want) in enumerate(cases):
        p = _write(tmp_path, f"t{i}.xml", body.format(cs=cs, cd=cd, v=v))
        c, o = read_transfer_function(p)([0.0])
        assert c[0, 0] == pytest.approx(want, abs=1e-8), (cs, cd, v)
        assert o[0] == 0.5


def test_xml_errors_and_warning(tmp_path):
    good_points = (
        '<OpacityPoints><OpacityPoint position="0" opacity="1"/></OpacityPoints>'
        '<ColorPoints color_data="float"><ColorPoint position="0" r="1" g="1" b="1"/></ColorPoints>'
    )
    p = _write(tmp_path, "a.xml",
               f'<TransferFunction colorspace="sRGB">{good_points}</TransferFunction>')
    with pytest.warns(UserWarning, match="interpolation_colorspace"):
        read_difftetvr_xml(p)

    p = _write(tmp_path, "b.xml",
               '<TransferFunction colorspace="HSV" interpolation_colorspace="Linear RGB">'
               f'{good_points}</TransferFunction>')
    with pytest.raises(ValueError, match="unknown colorspace"):
        read_difftetvr_xml(p)

    p = _write(tmp_path, "c.xml", f"<Foo>{good_points}</Foo>")
    with pytest.raises(ValueError, match="root element"):
        read_difftetvr_xml(p)

    p = _write(tmp_path, "d.xml", "<TransferFunction><OpacityPoints>")
    with pytest.raises(ValueError, match="malformed XML"):
        read_difftetvr_xml(p)

    p = _write(
        tmp_path,
        "e.xml",
        '<TransferFunction interpolation_colorspace="Linear RGB">'
        '<OpacityPoints><OpacityPoint position="0.5" opacity="1"/>'
        '<OpacityPoint position="0.1" opacity="1"/></OpacityPoints>'
        '<ColorPoints color_data="float"><ColorPoint position="0" r="1" g="1" b="1"/></ColorPoints>'
        '</TransferFunction>',
    )
    with pytest.raises(ValueError, match="non-decreasing"):
        read_difftetvr_xml(p)


# ----------------------------------------------------------------- JSON
def test_json_round_trip(tmp_path):
    tf = TransferFunction(
        [0.0, 0.1234567890123, 1.0],
        [[0.1, 0.2, 0.3], [1 / 3, 2 / 7, 0.0], [1.0, 1.0, 1.0]],
        [0.0, 0.3, 0.3, 1.0],
        [0.0, 0.0, 0.9, 0.25],
    )
    p = tmp_path / "tf.json"
    write_json(tf, p)
    data = json.loads(p.read_text())
    assert data["colorspace"] == "linear"
    tf2 = read_transfer_function(p)
    for name in ("color_positions", "colors", "opacity_positions", "opacities"):
        np.testing.assert_array_equal(getattr(tf2, name), getattr(tf, name))


def test_json_round_trip_of_xml(tmp_path):
    _need_data()
    tf = read_difftetvr_xml(TF_DIR / "Tooth3Gauss.xml")
    p = tmp_path / "g.json"
    write_json(tf, p)
    tf2 = read_json(p)
    t = np.linspace(-0.1, 1.1, 101)
    for a, b in zip(tf(t), tf2(t)):
        np.testing.assert_array_equal(a, b)


def test_json_srgb_and_default_colorspace(tmp_path):
    p = _write(tmp_path, "s.json", json.dumps(
        {"color": [[0, 0.5, 0.5, 0.5]], "opacity": [[0, 1]], "colorspace": "srgb"}))
    c, _ = read_json(p)([0.0])
    np.testing.assert_allclose(c[0], [0.21404114] * 3, atol=1e-8)
    p = _write(tmp_path, "l.json", json.dumps({"color": [[0, 0.5, 0.5, 0.5]], "opacity": [[0, 1]]}))
    c, _ = read_json(p)([0.0])
    np.testing.assert_allclose(c[0], [0.5] * 3)


@pytest.mark.parametrize(
    "obj, match",
    [
        ({"opacity": [[0, 1]]}, "missing key 'color'"),
        ({"color": [[0, 1, 1]], "opacity": [[0, 1]]}, r"\[pos, r, g, b\]"),
        ({"color": [[0, 1, 1, 1]], "opacity": [[0, 1, 2]]}, r"\[pos, a\]"),
        ({"color": [[0, 1, 1, 1]], "opacity": [[0, -1]]}, "opacities must be >= 0"),
        ({"color": [[0, 1, 1, 1]], "opacity": [[0, 1]], "colorspace": "lab"}, "unknown colorspace"),
        ({"tfEditor": {}}, "DiffDVR"),
        ([1, 2], "object"),
    ],
)
def test_json_bad_input(tmp_path, obj, match):
    p = _write(tmp_path, "bad.json", json.dumps(obj))
    with pytest.raises(ValueError, match=match):
        read_json(p)


def test_json_malformed(tmp_path):
    p = _write(tmp_path, "m.json", "{not json")
    with pytest.raises(ValueError, match="malformed JSON"):
        read_transfer_function(p)


def test_diffdvr_json_rejected_with_hint():
    p = DATA / "transfer-functions" / "diffdvr" / "tooth1.json"
    if not p.is_file():
        pytest.skip("DiffDVR json not available")
    with pytest.raises(ValueError, match="DiffTetVR XML"):
        read_transfer_function(p)


def test_texels_sample_the_function_at_texel_centres():
    """R texels hold the function at (k + 0.5) / R; a narrow peak between two
    control points is kept when the texels resolve it; fewer than 2 texels
    are refused."""
    tf = TransferFunction([0.0, 0.49, 0.5, 0.51, 1.0], np.eye(3)[[0, 0, 1, 0, 0]],
                          [0.0, 0.49, 0.5, 0.51, 1.0], [0.0, 0.0, 5.0, 0.0, 0.0])
    color, opacity = tf.texels(100)
    assert color.shape == (100, 3) and opacity.shape == (100,)
    centres = (np.arange(100) + 0.5) / 100
    ref_c, ref_o = tf(centres)
    np.testing.assert_allclose(color, ref_c)
    np.testing.assert_allclose(opacity, ref_o)
    # the peak at 0.5 falls between texel centres 0.495 and 0.505: half height
    np.testing.assert_allclose(opacity[49:51], [2.5, 2.5])
    assert opacity[:49].max() == 0 and opacity[51:].max() == 0
    with pytest.raises(ValueError, match="at least 2 texels"):
        tf.texels(1)


# -- colormaps as ParaView and matplotlib users have them ------------------------------
def _preset(tmp_path, **preset):
    path = tmp_path / "preset.json"
    path.write_text(json.dumps([{"Name": "test", **preset}]))
    return path


def test_paraview_rgb_preset_is_linear_in_srgb(tmp_path):
    """A ParaView preset in the RGB color space interpolates its (sRGB) points
    linearly, as ParaView shows them: at every sample the closed-form lerp; the
    points' range becomes [0, 1]; no 'Points': the opacity ramps 0 -> 1."""
    from mi_tetvr.color import linear_to_srgb
    from mi_tetvr.transfer import read_transfer_function
    tf = read_transfer_function(_preset(tmp_path, ColorSpace="RGB", RGBPoints=[
        10, 0.0, 0.2, 1.0, 20, 1.0, 0.6, 0.0, 30, 0.5, 0.5, 0.5]))
    t = np.arange(256) / 255
    c, o = tf(t)
    x = 10 + 20 * t
    expected = np.stack([np.interp(x, [10, 20, 30], k) for k in
                         ([0.0, 1.0, 0.5], [0.2, 0.6, 0.5], [1.0, 0.0, 0.5])], 1)
    np.testing.assert_allclose(linear_to_srgb(c), expected, atol=1e-6)
    np.testing.assert_allclose(o, t, atol=1e-12)


def test_paraview_diverging_preset_and_opacity_points(tmp_path):
    """ParaView's Cool to Warm (Moreland's diverging map, interpolated in Msh
    by VTK) passes through a neutral grey of about 0.865 at its middle;
    opacity points with midpoint 0.5 and sharpness 0 are piecewise linear."""
    from mi_tetvr.color import linear_to_srgb
    from mi_tetvr.transfer import read_paraview_json
    path = _preset(tmp_path, ColorSpace="Diverging",
                   RGBPoints=[-1, 0.23, 0.299, 0.754, 1, 0.706, 0.016, 0.15],
                   Points=[-1, 0.0, 0.5, 0.0, 0, 0.8, 0.5, 0.0, 1, 0.2, 0.5, 0.0])
    tf = read_paraview_json(path, samples=257)
    c, o = tf(np.array([0.0, 0.25, 0.5, 0.75, 1.0]))
    mid = linear_to_srgb(c[2])
    assert np.ptp(mid) < 2e-3 and abs(mid.mean() - 0.865) < 3e-3, mid
    np.testing.assert_allclose(linear_to_srgb(c[[0, 4]]), [[0.23, 0.299, 0.754],
                                                           [0.706, 0.016, 0.15]], atol=2e-3)
    np.testing.assert_allclose(o, [0.0, 0.4, 0.8, 0.5, 0.2], atol=1e-9)
    with pytest.raises(ValueError, match="RGBPoints"):
        read_paraview_json(_preset(tmp_path, RGBPoints=[0, 1, 1]))
    with pytest.raises(ValueError, match="ColorSpace"):
        read_paraview_json(_preset(tmp_path, ColorSpace="XYZ", RGBPoints=[0, 0, 0, 0, 1, 1, 1, 1]))


def test_matplotlib_colormap_by_name():
    """A matplotlib colormap's name: its colors at its own sample positions
    (sRGB, as matplotlib gives them), the opacity a ramp; an unknown name
    says what it accepts."""
    import matplotlib
    from mi_tetvr.color import linear_to_srgb
    from mi_tetvr.transfer import read_transfer_function
    t = np.arange(256) / 255
    for name in ("viridis", "coolwarm", "gray"):
        c, o = read_transfer_function(name)(t)
        np.testing.assert_allclose(linear_to_srgb(c), matplotlib.colormaps[name](t)[:, :3],
                                   atol=1e-6)
        np.testing.assert_allclose(o, t)
    with pytest.raises(ValueError, match="matplotlib colormap"):
        read_transfer_function("no_such_map")
