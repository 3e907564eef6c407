"""1D transfer functions that pre-shade a scalar field into per-vertex color and opacity.

A :class:`TransferFunction` holds two independent sets of piecewise-linear
control points on the normalised scalar axis ``[0, 1]``:

* color points ``color_positions`` (p,) with ``colors`` (p, 3) in **linear RGB**;
* opacity points ``opacity_positions`` (q,) with ``opacities`` (q,).

Color is always stored and interpolated in linear RGB.  The opacity is the
extinction coefficient per unit length used by the emission-absorption
renderer (before the global ``opacity_scale`` of :meth:`TransferFunction.shade`).
Outside the span of the control points the function is constant, equal to the
value at the first / last control point (this also clamps inputs outside
``[0, 1]``).  Two control points may share a position to encode a jump; at the
jump position itself the value after the jump is returned.

File formats
------------
:func:`read_transfer_function` reads either format by its suffix
(:func:`read_difftetvr_xml`, :func:`read_json`); :func:`write_json` writes the
project's.

DiffTetVR / sgl XML (``.xml``)::

    <TransferFunction colorspace="sRGB" interpolation_colorspace="Linear RGB">
        <OpacityPoints>
            <OpacityPoint position="0" opacity="1"/> ...
        </OpacityPoints>
        <ColorPoints color_data="ushort">
            <ColorPoint position="0" r="53853" g="53853" b="53853"/> ...
        </ColorPoints>
    </TransferFunction>

``color_data`` is one of ``ubyte`` (0..255, the sgl default when the attribute
is absent), ``ushort`` (0..65535), ``float`` (0..1) or ``float_255`` (0..255).
``colorspace`` is the space the color values are given in: ``sRGB`` (default;
converted with :func:`srgb_to_linear`) or ``Linear RGB`` (used as is).  This
module always interpolates in linear RGB; a file whose
``interpolation_colorspace`` is not ``Linear RGB`` is loaded with a
``UserWarning`` because DiffTetVR would interpolate it in sRGB.

Project JSON (``.json``)::

    {
      "color":   [[pos, r, g, b], ...],
      "opacity": [[pos, a], ...],
      "colorspace": "linear"
    }

``colorspace`` is ``"linear"`` (default when absent) or ``"srgb"``; it applies
to the ``r, g, b`` values (sRGB values are converted with
:func:`srgb_to_linear` on load).  :func:`write_json` always writes
``"linear"``.

ParaView colormap JSON (``.json``, what *Save as preset* / *Export* writes:
a list of presets, or one)::

    [{"Name": "Cool to Warm", "ColorSpace": "Diverging",
      "RGBPoints": [x, r, g, b, ...], "Points": [x, opacity, midpoint, sharpness, ...]}]

The first preset is read. Its colors (sRGB, as ParaView shows them) are
interpolated in its ``ColorSpace`` (RGB, HSV, Lab, Diverging, ...) by VTK's own
``vtkColorTransferFunction`` and its opacity points (with their midpoints and
sharpness) by ``vtkPiecewiseFunction``, both sampled at
:data:`COLORMAP_SAMPLES` positions over the points' range, which becomes the
normalised axis ``[0, 1]`` (ParaView too stretches a preset over the data
range). Without ``Points`` the opacity ramps from 0 to 1 (ParaView's default
for volumes).

A preset by name where no file of that name exists: the transfer functions
that ship with the package (:func:`presets`: ``default``, ``engine``,
``headmr``, ...; ``tf_NAME.json`` in :data:`BUNDLED`). Else a matplotlib
colormap by name (``"viridis"``, ``"coolwarm"``, ...): its colors sampled at
:data:`COLORMAP_SAMPLES` positions, the opacity a ramp from 0 to 1.

DiffDVR's JSON settings files (the ``tfEditor`` block) are deliberately *not*
supported: their colors are CIELAB, interpolated in CIELAB, with a separate
``opacityScaling`` and a Gaussian-mixture mode, so they are not representable
by linear-RGB piecewise-linear control points without resampling.  DiffTetVR
ships resampled conversions of the same tooth transfer functions as XML
(``Tooth1.xml``, ``Tooth3Gauss.xml``, ``Tooth3Linear.xml``); use those.
"""

from __future__ import annotations

import json
import warnings
import xml.etree.ElementTree as ET
from os import PathLike
from pathlib import Path
from typing import Tuple, Union

import numpy as np

from mi_tetvr.color import srgb_to_linear
from mi_tetvr.extras import needs

__all__ = ["TransferFunction", "read_transfer_function", "read_difftetvr_xml", "read_json",
           "read_paraview_json", "colormap", "presets", "write_json", "json_dict",
           "COLORMAP_SAMPLES", "BUNDLED"]

#: The package's bundled scenes and transfer functions: ``tf_NAME.json`` is the preset NAME.
BUNDLED = Path(__file__).resolve().parent / "scenes"

#: Control points a ParaView preset or a matplotlib colormap is sampled at.
COLORMAP_SAMPLES = 256

PathType = Union[str, "PathLike[str]"]

# Divisors for the sgl ``color_data`` attribute (see sgl's ColorDataMode).
_COLOR_DATA_DIVISORS = {
    "ubyte": 255.0,
    "ushort": 65535.0,
    "float": 1.0,
    "float_255": 255.0,
}


def _as_float_array(value, name: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric array-like: {exc}") from None
    return arr


def _check_positions(pos: np.ndarray, name: str) -> None:
    if pos.ndim != 1:
        raise ValueError(f"{name} must be a 1D array of shape (n,), got shape {pos.shape}")
    if pos.shape[0] == 0:
        raise ValueError(f"{name} must contain at least one control point")
    if not np.all(np.isfinite(pos)):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")
    if np.any(pos < 0.0) or np.any(pos > 1.0):
        raise ValueError(
            f"{name} must lie in [0, 1], got range [{pos.min()!r}, {pos.max()!r}]"
        )
    steps = np.diff(pos)
    if np.any(steps < 0.0):
        i = int(np.argmax(steps < 0.0))
        raise ValueError(
            f"{name} must be non-decreasing, but {name}[{i + 1}]={pos[i + 1]!r} "
            f"< {name}[{i}]={pos[i]!r}"
        )


class TransferFunction:
    """Piecewise-linear 1D transfer function on the normalised axis ``[0, 1]``.

    Parameters
    ----------
    color_positions : array_like, shape (p,)
        Positions of the color control points, in ``[0, 1]``, non-decreasing
        (equal neighbours encode a jump).
    colors : array_like, shape (p, 3)
        Linear-RGB colors at the color control points; finite and >= 0.
    opacity_positions : array_like, shape (q,)
        Positions of the opacity control points, in ``[0, 1]``, non-decreasing.
    opacities : array_like, shape (q,)
        Opacities (extinction per unit length, nominally in ``[0, 1]``) at the
        opacity control points; finite and >= 0.

    Raises
    ------
    ValueError
        On wrong shapes, empty point sets, non-finite values, positions outside
        ``[0, 1]`` or decreasing, negative colors or negative opacities.

    Notes
    -----
    Values at ``t`` outside the span of the control points (in particular
    ``t < 0`` or ``t > 1``) clamp to the first / last control point.  The
    stored arrays are read-only float64 copies.
    """

    def __init__(self, color_positions, colors, opacity_positions, opacities):
        cpos = _as_float_array(color_positions, "color_positions")
        cols = _as_float_array(colors, "colors")
        opos = _as_float_array(opacity_positions, "opacity_positions")
        opas = _as_float_array(opacities, "opacities")

        _check_positions(cpos, "color_positions")
        _check_positions(opos, "opacity_positions")

        if cols.ndim != 2 or cols.shape[1] != 3:
            raise ValueError(f"colors must have shape (p, 3), got shape {cols.shape}")
        if cols.shape[0] != cpos.shape[0]:
            raise ValueError(
                f"colors has {cols.shape[0]} rows but color_positions has "
                f"{cpos.shape[0]} entries; shapes must be (p, 3) and (p,)"
            )
        if not np.all(np.isfinite(cols)):
            raise ValueError("colors contains non-finite values (NaN or inf)")
        if np.any(cols < 0.0):
            raise ValueError(f"colors must be >= 0, got minimum {cols.min()!r}")

        if opas.ndim != 1:
            raise ValueError(f"opacities must have shape (q,), got shape {opas.shape}")
        if opas.shape[0] != opos.shape[0]:
            raise ValueError(
                f"opacities has {opas.shape[0]} entries but opacity_positions has "
                f"{opos.shape[0]}; both must have shape (q,)"
            )
        if not np.all(np.isfinite(opas)):
            raise ValueError("opacities contains non-finite values (NaN or inf)")
        if np.any(opas < 0.0):
            raise ValueError(f"opacities must be >= 0, got minimum {opas.min()!r}")

        for arr in (cpos, cols, opos, opas):
            arr.setflags(write=False)
        self.color_positions = cpos
        self.colors = cols
        self.opacity_positions = opos
        self.opacities = opas

    # ----------------------------------------------------------- evaluation
    def __call__(self, t) -> Tuple[np.ndarray, np.ndarray]:
        """Evaluate the transfer function.

        Parameters
        ----------
        t : array_like, shape (n,) (any shape is accepted)
            Normalised scalar values, nominally in ``[0, 1]``; values outside
            clamp to the end points.

        Returns
        -------
        color : numpy.ndarray, float64, shape (n, 3)
            Linear-RGB color (``t.shape + (3,)`` in general).
        opacity : numpy.ndarray, float64, shape (n,)
            Opacity (``t.shape`` in general).

        Raises
        ------
        ValueError
            If ``t`` contains NaN.
        """
        t = np.asarray(t, dtype=np.float64)
        if np.any(np.isnan(t)):
            raise ValueError("transfer function input t contains NaN")
        flat = np.clip(t.ravel(), 0.0, 1.0)
        color = np.empty((flat.shape[0], 3), dtype=np.float64)
        for ch in range(3):
            color[:, ch] = np.interp(flat, self.color_positions, self.colors[:, ch])
        opacity = np.interp(flat, self.opacity_positions, self.opacities)
        return color.reshape(t.shape + (3,)), opacity.reshape(t.shape)

    def shade(
        self, scalar, value_range=None, opacity_scale: float = 1.0
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Pre-shade a per-vertex scalar field into color and opacity.

        ``t = (scalar - lo) / (hi - lo)`` is evaluated with :meth:`__call__`
        (so values outside ``value_range`` clamp); if ``hi == lo`` every
        vertex gets ``t = 0``.

        Parameters
        ----------
        scalar : array_like, shape (n,) (any shape is accepted)
            Scalar value per vertex; must not contain NaN.
        value_range : (float, float), optional
            ``(lo, hi)`` mapped to ``[0, 1]``; finite with ``hi >= lo``.
            Default: ``(scalar.min(), scalar.max())``.
        opacity_scale : float, optional
            Finite, non-negative factor applied to the opacity (default 1).

        Returns
        -------
        color : numpy.ndarray, float64, shape (n, 3)
            Linear-RGB color per vertex.
        opacity : numpy.ndarray, float64, shape (n,)
            ``opacity_scale`` times the transfer-function opacity per vertex.

        Raises
        ------
        ValueError
            If ``scalar`` contains NaN (or is infinite with a default range),
            ``value_range`` is malformed, or ``opacity_scale`` is invalid.
        """
        s = np.asarray(scalar, dtype=np.float64)
        if np.any(np.isnan(s)):
            raise ValueError(f"scalar contains {int(np.isnan(s).sum())} NaN value(s)")
        scale = float(opacity_scale)
        if not np.isfinite(scale) or scale < 0.0:
            raise ValueError(f"opacity_scale must be finite and >= 0, got {opacity_scale!r}")

        if value_range is None:
            if not np.all(np.isfinite(s)):
                raise ValueError("scalar contains inf; pass an explicit value_range")
            lo, hi = (float(s.min()), float(s.max())) if s.size else (0.0, 0.0)
        else:
            try:
                lo, hi = (float(v) for v in value_range)
            except (TypeError, ValueError):
                raise ValueError(
                    f"value_range must be a pair (lo, hi) of numbers, got {value_range!r}"
                ) from None
            if not (np.isfinite(lo) and np.isfinite(hi)):
                raise ValueError(f"value_range must be finite, got {(lo, hi)!r}")
            if hi < lo:
                raise ValueError(f"value_range must satisfy lo <= hi, got {(lo, hi)!r}")

        if hi > lo:
            t = (s - lo) / (hi - lo)
        else:
            t = np.zeros_like(s)
        color, opacity = self(t)
        return color, opacity * scale

    @classmethod
    def from_texels(cls, color, opacity) -> "TransferFunction":
        """The transfer function of a texel table (the inverse of :meth:`texels`):
        control points at the texel centres ``(k + 0.5) / R``, piecewise linear
        between them and constant outside.

        Parameters
        ----------
        color : (R, 3) float, linear RGB
        opacity : (R,) float
        """
        color = np.asarray(color, np.float64).reshape(-1, 3)
        opacity = np.asarray(opacity, np.float64).reshape(-1)
        if len(color) != len(opacity) or len(opacity) < 2:
            raise ValueError(f"a texel table needs R >= 2 colors and opacities, got "
                             f"{len(color)} and {len(opacity)}")
        pos = (np.arange(len(opacity)) + 0.5) / len(opacity)
        return cls(pos, color, pos, opacity)

    def texels(self, resolution: int = 256) -> Tuple[np.ndarray, np.ndarray]:
        """The transfer function resampled to ``resolution`` regular texels:
        texel ``k`` holds the value at ``(k + 0.5) / resolution`` of the
        normalised axis; the texel table is read piecewise linearly between
        texel centres and clamped outside them (what post-classified
        rendering uses).

        Returns
        -------
        color : (resolution, 3) float64, linear RGB
        opacity : (resolution,) float64
        """
        resolution = int(resolution)
        if resolution < 2:
            raise ValueError(f"the transfer function needs at least 2 texels, got {resolution}")
        return self((np.arange(resolution) + 0.5) / resolution)

    def __repr__(self) -> str:
        return (
            f"TransferFunction({self.color_positions.shape[0]} color points, "
            f"{self.opacity_positions.shape[0]} opacity points)"
        )


# ------------------------------------------------------------------------ files
def read_transfer_function(path: PathType) -> TransferFunction:
    """Read a transfer function file, dispatching on its suffix and content,
    or a matplotlib colormap by name.

    Parameters
    ----------
    path : str or os.PathLike
        ``.xml`` (DiffTetVR / sgl format, :func:`read_difftetvr_xml`),
        ``.json`` (the project's format, :func:`read_json`, or a ParaView
        colormap preset, :func:`read_paraview_json`); the suffix is matched
        case-insensitively. A name that is no file is a preset of the
        package (:func:`presets`: ``default``, ``engine``, ...) or a
        matplotlib colormap's (``viridis``, :func:`colormap`).

    Returns
    -------
    TransferFunction

    Raises
    ------
    ValueError
        If the suffix is neither ``.xml`` nor ``.json`` (and the name no
        colormap's), or the file is malformed.
    """
    suffix = Path(path).suffix.lower()
    if not Path(path).exists() and suffix not in (".xml", ".json"):
        preset = BUNDLED / f"tf_{path}.json"
        if preset.is_file():
            return read_json(preset)
        return colormap(str(path))
    if suffix == ".xml":
        return read_difftetvr_xml(path)
    if suffix == ".json":
        return read_json(path)
    raise ValueError(
        f"unknown transfer function file suffix {Path(path).suffix!r} for "
        f"{str(path)!r}; expected '.xml' (DiffTetVR) or '.json' (the project's or a "
        f"ParaView colormap), or a matplotlib colormap's name"
    )


def presets():
    """The names of the transfer functions that ship with the package
    (:func:`read_transfer_function` reads each by its name)."""
    return sorted(p.stem[3:] for p in BUNDLED.glob("tf_*.json"))


def _ramp(n: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, n)


def colormap(name: str, samples: int = COLORMAP_SAMPLES) -> TransferFunction:
    """A matplotlib colormap by name: its sRGB colors sampled at ``samples``
    positions over ``[0, 1]`` (stored linear), the opacity a ramp from 0 to 1."""
    with needs("vis", "a matplotlib colormap by name"):
        import matplotlib
    try:
        cmap = matplotlib.colormaps[name]
    except KeyError:
        raise ValueError(f"{name!r} is no transfer function file, no preset of mi_tetvr "
                         f"({', '.join(presets())}) and no matplotlib colormap (e.g. "
                         f"viridis, plasma, coolwarm, gray)") from None
    x = _ramp(samples)
    return TransferFunction(x, srgb_to_linear(np.asarray(cmap(x))[:, :3]), x, x.copy())


def read_paraview_json(path: PathType, samples: int = COLORMAP_SAMPLES) -> TransferFunction:
    """A ParaView colormap preset (see the module docstring), interpolated as
    ParaView does by VTK's ``vtkColorTransferFunction`` (in the preset's
    ``ColorSpace``) and ``vtkPiecewiseFunction``, sampled at ``samples``
    positions over the range of its ``RGBPoints``."""
    try:
        with open(path, "r", encoding="utf-8") as f:
            data = json.load(f)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{str(path)!r}: malformed JSON: {exc}") from None
    return _paraview_preset(data[0] if isinstance(data, list) and data else data, str(path),
                            samples)


def _paraview_preset(preset, where: str, samples: int) -> TransferFunction:
    with needs("vis", "reading a ParaView colormap preset"):
        from vtkmodules.vtkRenderingCore import vtkColorTransferFunction
        from vtkmodules.vtkCommonDataModel import vtkPiecewiseFunction
    if not isinstance(preset, dict):
        raise ValueError(f"{where!r}: the JSON value must be an object (the project's format) "
                         f"or a list of ParaView presets (objects with 'RGBPoints')")
    rgb = np.asarray(preset.get("RGBPoints", []), float)
    if rgb.size < 8 or rgb.size % 4:
        raise ValueError(f"{where!r}: a ParaView preset needs 'RGBPoints' [x, r, g, b, ...] "
                         f"with two points or more")
    rgb = rgb.reshape(-1, 4)
    lo, hi = float(rgb[:, 0].min()), float(rgb[:, 0].max())
    if not hi > lo:
        raise ValueError(f"{where!r}: the 'RGBPoints' span no range ({lo:g} .. {hi:g})")
    ctf = vtkColorTransferFunction()
    space = str(preset.get("ColorSpace", "RGB")).lower()
    setters = {"rgb": ctf.SetColorSpaceToRGB, "hsv": ctf.SetColorSpaceToHSV,
               "lab": ctf.SetColorSpaceToLab, "cielab": ctf.SetColorSpaceToLab,
               "diverging": ctf.SetColorSpaceToDiverging,
               "lab/ciede2000": ctf.SetColorSpaceToLabCIEDE2000,
               "step": ctf.SetColorSpaceToStep}
    if space not in setters:
        raise ValueError(f"{where!r}: unknown ColorSpace {preset.get('ColorSpace')!r} "
                         f"(one of {sorted(setters)})")
    setters[space]()
    if preset.get("HSVWrap") is not None and space == "hsv":
        ctf.SetHSVWrap(bool(preset["HSVWrap"]))
    for x, r, g, b in rgb:
        ctf.AddRGBPoint(float(x), float(r), float(g), float(b))
    x = lo + _ramp(samples) * (hi - lo)
    colors = np.array([ctf.GetColor(float(v)) for v in x])
    points = np.asarray(preset.get("Points", []), float)
    if points.size:
        if points.size % 4:
            raise ValueError(f"{where!r}: 'Points' must be [x, opacity, midpoint, sharpness, "
                             f"...]")
        pwf = vtkPiecewiseFunction()
        for px, py, mid, sharp in points.reshape(-1, 4):
            pwf.AddPoint(float(px), float(py), float(mid), float(sharp))
        opacity = np.array([pwf.GetValue(float(v)) for v in x])
    else:
        opacity = _ramp(samples)
    t = _ramp(samples)
    return TransferFunction(t, srgb_to_linear(np.clip(colors, 0.0, 1.0)), t, opacity)


def read_difftetvr_xml(path: PathType) -> TransferFunction:
    """Load a DiffTetVR / sgl ``<TransferFunction>`` XML file.

    Colors are converted to linear RGB according to the ``colorspace``
    and ``color_data`` attributes (see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    TransferFunction

    Raises
    ------
    ValueError
        On XML syntax errors, a wrong root tag, missing point lists or
        attributes, unknown ``colorspace`` / ``color_data`` values, or
        invalid control points.
    """
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"{str(path)!r}: malformed XML: {exc}") from None
    if root.tag != "TransferFunction":
        raise ValueError(
            f"{str(path)!r}: root element must be <TransferFunction>, got <{root.tag}>"
        )

    colorspace = root.get("colorspace", "sRGB")
    if colorspace not in ("sRGB", "Linear RGB"):
        raise ValueError(
            f"{str(path)!r}: unknown colorspace {colorspace!r}; "
            "expected 'sRGB' or 'Linear RGB'"
        )
    interp = root.get("interpolation_colorspace", "sRGB")
    if interp != "Linear RGB":
        warnings.warn(
            f"{str(path)!r}: interpolation_colorspace={interp!r}, but colors are "
            "always interpolated in linear RGB here; results between control "
            "points differ from DiffTetVR",
            UserWarning,
            stacklevel=2,
        )

    color_node = root.find("ColorPoints")
    if color_node is None:
        raise ValueError(f"{str(path)!r}: missing <ColorPoints>")
    color_data = color_node.get("color_data", "ubyte")
    if color_data not in _COLOR_DATA_DIVISORS:
        raise ValueError(
            f"{str(path)!r}: unknown color_data {color_data!r}; expected one of "
            f"{sorted(_COLOR_DATA_DIVISORS)}"
        )
    if root.find("OpacityPoints") is None:
        raise ValueError(f"{str(path)!r}: missing <OpacityPoints>")

    def attr(node: ET.Element, key: str) -> float:
        value = node.get(key)
        if value is None:
            raise ValueError(f"{str(path)!r}: <{node.tag}> lacks attribute {key!r}")
        try:
            return float(value)
        except ValueError:
            raise ValueError(
                f"{str(path)!r}: <{node.tag}> attribute {key}={value!r} is not a number"
            ) from None

    color_nodes = color_node.findall("ColorPoint")
    cpos = [attr(n, "position") for n in color_nodes]
    cols = np.array(
        [[attr(n, "r"), attr(n, "g"), attr(n, "b")] for n in color_nodes],
        dtype=np.float64,
    ).reshape(-1, 3)
    cols = cols / _COLOR_DATA_DIVISORS[color_data]
    if colorspace == "sRGB":
        cols = srgb_to_linear(cols)

    opacity_nodes = root.findall("OpacityPoints/OpacityPoint")
    opos = [attr(n, "position") for n in opacity_nodes]
    opas = [attr(n, "opacity") for n in opacity_nodes]
    try:
        return TransferFunction(cpos, cols, opos, opas)
    except ValueError as exc:
        raise ValueError(f"{str(path)!r}: {exc}") from None


def read_json(path: PathType) -> TransferFunction:
    """Load the project's JSON format (see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    TransferFunction

    Raises
    ------
    ValueError
        On malformed JSON, missing keys, rows of the wrong length, an
        unknown ``colorspace``, invalid control points, or a DiffDVR
        settings file (not supported; use DiffTetVR's XML conversion).
    """
    try:
        with open(path, "r", encoding="utf-8") as f:
            data = json.load(f)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{str(path)!r}: malformed JSON: {exc}") from None
    if isinstance(data, list) or (isinstance(data, dict) and "RGBPoints" in data):
        return _paraview_preset(data[0] if isinstance(data, list) and data else data, str(path),
                                COLORMAP_SAMPLES)
    if not isinstance(data, dict):
        raise ValueError(f"{str(path)!r}: top-level JSON value must be an object")
    if "tfEditor" in data:
        raise ValueError(
            f"{str(path)!r} is a DiffDVR settings file (CIELAB colors interpolated "
            "in CIELAB, separate opacityScaling); it is not supported. Use the "
            "DiffTetVR XML conversion of the same transfer function instead."
        )
    for key in ("color", "opacity"):
        if key not in data:
            raise ValueError(f"{str(path)!r}: missing key {key!r}")
    colorspace = str(data.get("colorspace", "linear")).lower()
    if colorspace not in ("linear", "srgb"):
        raise ValueError(
            f"{str(path)!r}: unknown colorspace {data.get('colorspace')!r}; "
            "expected 'linear' or 'srgb'"
        )

    if not _rows_ok(data["color"], 4):
        raise ValueError(f"{str(path)!r}: 'color' must be a non-empty list of [pos, r, g, b] rows")
    if not _rows_ok(data["opacity"], 2):
        raise ValueError(f"{str(path)!r}: 'opacity' must be a non-empty list of [pos, a] rows")
    color = np.array(data["color"], dtype=np.float64)
    opacity = np.array(data["opacity"], dtype=np.float64)

    cols = color[:, 1:]
    if colorspace == "srgb":
        cols = srgb_to_linear(cols)
    try:
        return TransferFunction(color[:, 0], cols, opacity[:, 0], opacity[:, 1])
    except ValueError as exc:
        raise ValueError(f"{str(path)!r}: {exc}") from None


def json_dict(tf: TransferFunction) -> dict:
    """The project's JSON format of ``tf`` as a dict (``"colorspace": "linear"``,
    floats as Python floats)."""
    return {
        "colorspace": "linear",
        "color": [
            [float(p), float(c[0]), float(c[1]), float(c[2])]
            for p, c in zip(tf.color_positions, tf.colors)
        ],
        "opacity": [
            [float(p), float(a)] for p, a in zip(tf.opacity_positions, tf.opacities)
        ],
    }


def write_json(tf: TransferFunction, path: PathType) -> None:
    """Write ``tf`` in the project's JSON format with ``"colorspace": "linear"``.

    Floats are written with full (round-trip exact) precision.

    Parameters
    ----------
    tf : TransferFunction
    path : str or os.PathLike
    """
    with open(path, "w", encoding="utf-8") as f:
        json.dump(json_dict(tf), f, indent=2)
        f.write("\n")


def _rows_ok(rows, width: int) -> bool:
    """True if ``rows`` is a non-empty list of length-``width`` numeric lists."""
    if not isinstance(rows, (list, tuple)) or len(rows) == 0:
        return False
    for row in rows:
        if not isinstance(row, (list, tuple)) or len(row) != width:
            return False
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in row):
            return False
    return True
