"""Scalar volumes on regular grids, a Dr.Jit grid ray marcher and multi-view data sets.

This module provides the ground truth for reconstruction (images of a regular-grid scalar
volume under a transfer function) and the grid baseline for comparisons with the tet renderer.

Conventions
-----------
Layout
    ``Volume.values`` is a float32 array of shape ``(nz, ny, nx)`` in C order, i.e. **x is
    the fastest axis** (``values[k, j, i]`` is the sample at grid index ``(i, j, k)``), the
    layout of raw files, DiffDVR ``.cvol``, MetaImage and VTK image data.  ``spacing`` and
    ``origin`` are given in ``(x, y, z)`` order.
Samples are nodes
    The value ``values[k, j, i]`` sits at the world point ``origin + (i, j, k) * spacing``
    and is interpolated **trilinearly** between nodes, so the volume's box spans the nodes:
    ``[origin, origin + (n - 1) * spacing]`` (the same field a tet mesh on the grid nodes
    with linear interpolation represents, up to the trilinear vs. linear difference).
World placement
    :func:`make_volume` / :func:`load_volume` centre the box at the origin and scale it
    uniformly so that its largest extent is 2, i.e. it lies in ``[-1, 1]^3`` and touches
    ``+-1`` along its longest axis; the voxel aspect ratio from the file's spacing is kept.
    Grid x, y, z are world x, y, z.
Normalisation
    Values are mapped to ``[0, 1]`` by ``(v - lo) / (hi - lo)`` with ``(lo, hi)`` the data
    range (default: ``(min, max)`` of the data; pass ``value_range=`` to fix it, e.g.
    ``(0, 255)`` for uint8) and clipped to ``[0, 1]``.  ``Volume.data_range`` records
    ``(lo, hi)``.
Rendering model (post-classification emission-absorption)
    Along a ray the box is entered at ``t0`` and left at ``t1`` (slab test); the marcher
    takes steps of ``dt = step * min(spacing)`` (``step`` in voxels, default 0.25; the last
    step is shortened to end exactly at ``t1``) and samples the **midpoint** of each step:
    the scalar is interpolated trilinearly, *then* the transfer function gives the linear-RGB
    colour ``c`` and the extinction ``sigma`` (``TransferFunction`` opacity times
    ``opacity_scale``, per unit length in the world units of the ``[-1, 1]`` placement).
    Per step ``a = exp(-sigma * h)``, ``C += T * c * (1 - a)``, ``T *= a`` (the exact
    integral for ``c`` and ``sigma`` held constant over the step, as in the tet renderer's
    sub-intervals).  The output is premultiplied linear RGB over black plus
    ``alpha = 1 - T``.  Rays stop early once ``T < min_transmittance`` (default 1e-4, the
    tet integrator's default).  The midpoint rule makes the transmittance exact for an
    extinction linear along the step; the error is O(dt^2) in general.
Transfer function
    Evaluated exactly inside Dr.Jit from its piecewise-linear control points (no lookup
    table): ``t = (s - lo) / (hi - lo)`` with ``value_range=(lo, hi)`` (default ``(0, 1)``,
    i.e. the normalised scalar), clamped like :meth:`TransferFunction.__call__`.
Cameras
    :class:`mi_tetvr.recon.datasets.View` (without image): camera-to-world in **Mitsuba axes**
    (camera looks along +z, +y is up in the image, +x is *left* in the image; what
    ``mi.ScalarTransform4f().look_at`` builds) and pinhole intrinsics in pixels.  Pixel
    ``(px, py)`` (``py`` from the top) is sampled at its centre.
Data sets (NeRF-synthetic convention)
    ``transforms_{train,test}.json`` with ``camera_angle_x`` (radians), ``fl_x, fl_y, cx,
    cy, w, h`` (pixels) and per frame ``file_path`` (``./train/r_0``, without extension as in
    NeRF-synthetic; the image is ``train/r_0.png``) and ``transform_matrix`` (OpenGL
    camera-to-world).  Images are 8-bit RGBA PNG with **straight** (un-premultiplied) alpha
    and sRGB-encoded colour: ``rgb_png = srgb(C / alpha)``, ``alpha_png = alpha``.
"""
from __future__ import annotations

import dataclasses
import gzip
import json
import math
import re
import struct
import zlib
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.recon.datasets import Dataset, View, look_at, write_nerf
from mi_tetvr.transfer import TransferFunction

__all__ = [
    "Volume", "make_volume", "load_volume", "write_cvol", "write_mhd",
    "look_at", "fibonacci_cameras", "random_cameras", "default_fov",
    "render_volume", "render_rays", "camera_rays", "GridField", "TFEval",
    "make_dataset", "trilinear_numpy",
]

PathType = Union[str, "PathLike[str]"]


# ============================================================================ volumes
@dataclass
class Volume:
    """A scalar field on a regular grid, placed in world space.

    Attributes
    ----------
    values : (nz, ny, nx) float32
        Normalised scalar in ``[0, 1]``, x fastest (see the module docstring).
    spacing : (3,) float64
        World distance between neighbouring samples along x, y, z.
    origin : (3,) float64
        World position of the sample ``values[0, 0, 0]``.
    data_range : (float, float)
        Raw values mapped to 0 and 1.
    source : str
        Where the data came from (a path or ``"array"``).
    source_spacing : (3,) float64
        Sample spacing given by the source (physical units), x, y, z.
    """

    values: np.ndarray
    spacing: np.ndarray
    origin: np.ndarray
    data_range: Tuple[float, float] = (0.0, 1.0)
    source: str = "array"
    source_spacing: np.ndarray = field(default_factory=lambda: np.ones(3))

    @property
    def shape(self) -> Tuple[int, int, int]:
        """Grid size ``(nx, ny, nz)``."""
        nz, ny, nx = self.values.shape
        return nx, ny, nz

    def bounds(self) -> Tuple[np.ndarray, np.ndarray]:
        """World-space box ``(lo (3,), hi (3,))`` spanned by the sample nodes."""
        lo = np.asarray(self.origin, np.float64)
        return lo, lo + (np.array(self.shape) - 1) * np.asarray(self.spacing, np.float64)

    def world_to_index(self, p) -> np.ndarray:
        """Continuous grid index ``(i, j, k)`` (x, y, z) of world points ``p (..., 3)``."""
        return (np.asarray(p, np.float64) - self.origin) / self.spacing

    def sample(self, p) -> np.ndarray:
        """Trilinear interpolation at world points ``p (..., 3)`` (numpy reference; clamps)."""
        return trilinear_numpy(self.values, self.world_to_index(p))

    def info(self) -> dict:
        lo, hi = self.bounds()
        return {"source": self.source, "shape_xyz": list(self.shape),
                "data_range": [float(v) for v in self.data_range],
                "source_spacing": [float(v) for v in self.source_spacing],
                "spacing": [float(v) for v in self.spacing],
                "origin": [float(v) for v in self.origin],
                "bounds": [[float(v) for v in lo], [float(v) for v in hi]]}


def trilinear_numpy(values: np.ndarray, idx) -> np.ndarray:
    """Trilinear interpolation of ``values (nz, ny, nx)`` at continuous indices.

    ``idx (..., 3)`` holds ``(i, j, k)`` (x, y, z) grid coordinates; they are clamped to the
    grid.  Returns float64 of shape ``idx.shape[:-1]``.
    """
    v = np.asarray(values, np.float64)
    n = np.array(v.shape[::-1])
    g = np.clip(np.asarray(idx, np.float64), 0, n - 1)
    i0 = np.clip(np.floor(g).astype(np.int64), 0, np.maximum(n - 2, 0))
    f = g - i0
    out = 0.0
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                w = ((f[..., 0] if dx else 1 - f[..., 0]) * (f[..., 1] if dy else 1 - f[..., 1])
                     * (f[..., 2] if dz else 1 - f[..., 2]))
                ii = np.minimum(i0 + [dx, dy, dz], n - 1)
                out = out + w * v[ii[..., 2], ii[..., 1], ii[..., 0]]
    return out


def make_volume(values, spacing=(1.0, 1.0, 1.0), value_range=None, source: str = "array",
                layout: str = "zyx") -> Volume:
    """Normalise a scalar grid to ``[0, 1]`` and place it in ``[-1, 1]^3``.

    Parameters
    ----------
    values : (nz, ny, nx) array_like (or (nx, ny, nz) with ``layout="xyz"``)
        Raw scalar samples; at least 2 samples per axis, finite.
    spacing : (3,) float
        Sample spacing along x, y, z (physical units; only the ratios matter).
    value_range : (lo, hi), optional
        Raw values mapped to 0 and 1 (clipped outside).  Default: data min and max.
    source : str
        Recorded in ``Volume.source``.
    layout : ``"zyx"`` (default, x fastest) or ``"xyz"``
        Axis order of ``values``.
    """
    v = np.asarray(values)
    if v.ndim != 3:
        raise ValueError(f"volume values must be 3D, got shape {v.shape}")
    if layout == "xyz":
        v = v.transpose(2, 1, 0)
    elif layout != "zyx":
        raise ValueError(f"layout must be 'zyx' or 'xyz', got {layout!r}")
    if min(v.shape) < 2:
        raise ValueError(f"need at least 2 samples per axis, got shape (nz, ny, nx)={v.shape}")
    v = v.astype(np.float64)
    if not np.all(np.isfinite(v)):
        raise ValueError("volume values contain NaN or inf")
    if value_range is None:
        lo, hi = float(v.min()), float(v.max())
    else:
        lo, hi = (float(x) for x in value_range)
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
            raise ValueError(f"value_range must be finite with lo <= hi, got {value_range!r}")
    norm = np.clip((v - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(v)

    sp = np.asarray(spacing, np.float64).reshape(3)
    if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise ValueError(f"spacing must be finite and > 0, got {spacing!r}")
    extent = (np.array(v.shape[::-1]) - 1) * sp
    scale = 2.0 / extent.max()
    return Volume(values=np.ascontiguousarray(norm, np.float32), spacing=sp * scale,
                  origin=-0.5 * extent * scale, data_range=(lo, hi), source=str(source),
                  source_spacing=sp)


_DTYPES = {"uint8": "u1", "int8": "i1", "uint16": "<u2", "int16": "<i2", "uint32": "<u4",
           "int32": "<i4", "float32": "<f4", "float": "<f4", "float64": "<f8",
           "double": "<f8"}


def _read_bytes(path: Path) -> bytes:
    if path.suffix.lower() == ".gz":
        with gzip.open(path, "rb") as f:
            return f.read()
    return path.read_bytes()


def _load_raw(path: Path, shape, dtype):
    name = path.name
    if shape is None:
        m = re.search(r"(\d+)x(\d+)x(\d+)", name)
        if not m:
            raise ValueError(f"{str(path)!r}: a raw file needs shape=(nx, ny, nz) "
                             "(or dims like '256x256x128' in the file name)")
        shape = tuple(int(s) for s in m.groups())
    if dtype is None:
        m = re.search(r"(uint8|int8|uint16|int16|uint32|int32|float32|float64)", name)
        if not m:
            raise ValueError(f"{str(path)!r}: a raw file needs dtype= (or a dtype like "
                             "'uint8' in the file name)")
        dtype = m.group(1)
    dt = np.dtype(_DTYPES.get(str(dtype), dtype))
    nx, ny, nz = (int(s) for s in shape)
    data = _read_bytes(path)
    if len(data) != nx * ny * nz * dt.itemsize:
        raise ValueError(f"{str(path)!r}: {len(data)} bytes, expected {nx}*{ny}*{nz}*"
                         f"{dt.itemsize} for shape (nx, ny, nz)={shape}, dtype {dt}")
    return np.frombuffer(data, dt).reshape(nz, ny, nx), np.ones(3)


_CVOL_TYPES = {0: np.uint8, 1: np.dtype("<u2"), 2: np.dtype("<f4")}


def _load_cvol(path: Path):
    data = path.read_bytes()
    if len(data) < 64 or data[:4] != b"cvol":
        raise ValueError(f"{str(path)!r}: not a DiffDVR .cvol file (magic 'cvol' missing)")
    nx, ny, nz = struct.unpack_from("<3Q", data, 4)
    vs = struct.unpack_from("<3d", data, 28)
    (typ,) = struct.unpack_from("<i", data, 52)
    compressed = data[56]
    if typ not in _CVOL_TYPES:
        raise ValueError(f"{str(path)!r}: unknown cvol data type {typ} (0 uint8, 1 uint16, 2 float)")
    dt = np.dtype(_CVOL_TYPES[typ])
    if compressed:
        # DiffDVR's lz4cpp chunk framing is not verified against a real file: refuse.
        raise ValueError(f"{str(path)!r}: LZ4-compressed .cvol (DiffDVR lz4cpp chunk framing) "
                         "is not supported; re-save it uncompressed")
    n = nx * ny * nz
    if len(data) - 64 < n * dt.itemsize:
        raise ValueError(f"{str(path)!r}: truncated ({len(data) - 64} data bytes, "
                         f"expected {n * dt.itemsize})")
    # DiffDVR's CPU tensor (X, Y, Z) has strides (1, X, X*Y): x is fastest in the file.
    v = np.frombuffer(data, dt, count=n, offset=64).reshape(nz, ny, nx)
    return v, np.array(vs, np.float64)


def write_cvol(path: PathType, values, voxel_size=(1.0, 1.0, 1.0)) -> None:
    """Write an uncompressed DiffDVR ``.cvol`` (uint8, uint16 or float32 ``values (nz, ny, nx)``)."""
    v = np.asarray(values)
    typ = {np.dtype(np.uint8): 0, np.dtype(np.uint16): 1, np.dtype(np.float32): 2}.get(v.dtype)
    if typ is None:
        raise ValueError(f"cvol stores uint8, uint16 or float32, not {v.dtype}")
    nz, ny, nx = v.shape
    head = b"cvol" + struct.pack("<3Q3di", nx, ny, nz, *map(float, voxel_size), typ) + b"\0" * 8
    assert len(head) == 64
    with open(path, "wb") as f:
        f.write(head)
        f.write(np.ascontiguousarray(v).astype(v.dtype.newbyteorder("<")).tobytes())


_MET_TYPES = {"MET_UCHAR": "u1", "MET_CHAR": "i1", "MET_USHORT": "u2", "MET_SHORT": "i2",
              "MET_UINT": "u4", "MET_INT": "i4", "MET_ULONG_LONG": "u8", "MET_LONG_LONG": "i8",
              "MET_FLOAT": "f4", "MET_DOUBLE": "f8"}


def _load_mhd(path: Path):
    text = path.read_bytes()
    header = {}
    offset = 0
    for line in text.split(b"\n"):
        offset += len(line) + 1
        s = line.decode("latin-1").strip()
        if "=" not in s:
            continue
        k, val = (x.strip() for x in s.split("=", 1))
        header[k] = val
        if k == "ElementDataFile":
            break
    try:
        dims = [int(x) for x in header["DimSize"].split()]
        etype = header["ElementType"]
        datafile = header["ElementDataFile"]
    except KeyError as exc:
        raise ValueError(f"{str(path)!r}: MetaImage header lacks {exc}") from None
    if len(dims) != 3 or int(header.get("NDims", 3)) != 3:
        raise ValueError(f"{str(path)!r}: only 3D MetaImages are supported (DimSize={dims})")
    if int(header.get("ElementNumberOfChannels", 1)) != 1:
        raise ValueError(f"{str(path)!r}: only single-channel MetaImages are supported")
    if etype not in _MET_TYPES:
        raise ValueError(f"{str(path)!r}: unsupported ElementType {etype}")
    msb = header.get("ElementByteOrderMSB", header.get("BinaryDataByteOrderMSB", "False"))
    dt = np.dtype(_MET_TYPES[etype]).newbyteorder(">" if msb.lower() == "true" else "<")
    sp = header.get("ElementSpacing", header.get("ElementSize", "1 1 1"))
    spacing = np.array([float(x) for x in sp.split()], np.float64)
    if datafile == "LOCAL":
        raw = text[offset:]
    elif datafile.startswith("LIST") or "%" in datafile:
        raise ValueError(f"{str(path)!r}: multi-file MetaImages are not supported")
    else:
        raw = (path.parent / datafile).read_bytes()
    if header.get("CompressedData", "False").lower() == "true":
        raw = zlib.decompress(raw)
    skip = int(header.get("HeaderSize", 0))
    n = int(np.prod(dims))
    if skip == -1:
        skip = len(raw) - n * dt.itemsize
    if len(raw) - skip < n * dt.itemsize:
        raise ValueError(f"{str(path)!r}: data has {len(raw) - skip} bytes, expected "
                         f"{n * dt.itemsize}")
    nx, ny, nz = dims
    return np.frombuffer(raw, dt, count=n, offset=skip).reshape(nz, ny, nx), spacing


def write_mhd(path: PathType, values, spacing=(1.0, 1.0, 1.0)) -> None:
    """Write ``values (nz, ny, nx)`` as MetaImage ``path`` (.mhd) plus ``path.raw``."""
    path = Path(path)
    v = np.ascontiguousarray(values)
    inv = {np.dtype(t).newbyteorder("<"): k for k, t in _MET_TYPES.items()}
    key = v.dtype.newbyteorder("<")
    if key not in inv:
        raise ValueError(f"unsupported dtype {v.dtype}")
    nz, ny, nx = v.shape
    raw = path.with_suffix(".raw")
    path.write_text(
        "ObjectType = Image\nNDims = 3\n"
        f"DimSize = {nx} {ny} {nz}\n"
        f"ElementSpacing = {' '.join(repr(float(s)) for s in spacing)}\n"
        f"ElementType = {inv[key]}\nElementByteOrderMSB = False\n"
        f"ElementDataFile = {raw.name}\n")
    raw.write_bytes(v.astype(key).tobytes())


def _load_vtk_image(path: Path):
    import pyvista as pv
    img = pv.read(str(path))
    if not isinstance(img, pv.ImageData):
        raise ValueError(f"{str(path)!r}: not VTK image data (got {type(img).__name__})")
    nx, ny, nz = img.dimensions
    if img.point_data.keys():
        name = img.point_data.active_scalars_name or img.point_data.keys()[0]
        arr = np.asarray(img.point_data[name])
    else:
        raise ValueError(f"{str(path)!r}: no point data (cell-data images are not supported)")
    if arr.ndim != 1:
        raise ValueError(f"{str(path)!r}: point array {name!r} is not scalar (shape {arr.shape})")
    return arr.reshape(nz, ny, nx), np.array(img.spacing, np.float64)


def load_volume(path: PathType, shape=None, dtype=None, spacing=None,
                value_range=None) -> Volume:
    """Load a scalar grid, normalise it to ``[0, 1]`` and place it in ``[-1, 1]^3``.

    Parameters
    ----------
    path : str or PathLike
        ``.raw`` / ``.raw.gz`` (x fastest; dims and dtype from ``shape``/``dtype`` or from
        the file name, e.g. ``engine_256x256x128_uint8.raw.gz``), ``.npy`` (an array of
        shape ``(nz, ny, nx)``), DiffDVR ``.cvol`` (uncompressed), MetaImage ``.mhd``/``.mha``,
        VTK image data ``.vti`` (point data; via pyvista).
    shape : (nx, ny, nz), optional
        Grid size of a raw file.
    dtype : str or numpy dtype, optional
        Sample type of a raw file (``uint8``, ``uint16``, ``float32``, ...; little endian).
    spacing : (3,) float, optional
        Override the file's sample spacing (x, y, z).
    value_range : (lo, hi), optional
        Raw values mapped to 0 and 1 (default: the data's min and max).

    Returns
    -------
    Volume
    """
    path = Path(path)
    name = path.name.lower()
    if name.endswith(".npy"):
        v, sp = np.load(path), np.ones(3)
    elif name.endswith(".cvol"):
        v, sp = _load_cvol(path)
    elif name.endswith(".mhd") or name.endswith(".mha"):
        v, sp = _load_mhd(path)
    elif name.endswith(".vti") or name.endswith(".vtk"):
        v, sp = _load_vtk_image(path)
    elif name.endswith(".raw") or name.endswith(".raw.gz") or name.endswith(".dat") \
            or shape is not None:
        v, sp = _load_raw(path, shape, dtype)
    else:
        raise ValueError(f"{str(path)!r}: unknown volume format (expected .raw[.gz], .npy, "
                         ".cvol, .mhd/.mha or .vti)")
    if spacing is not None:
        sp = spacing
    return make_volume(v, spacing=sp, value_range=value_range, source=str(path))


# ============================================================================ cameras
def default_fov(radius: float, margin: float = 1.05) -> float:
    """Horizontal fov (degrees) whose cone at distance ``radius`` holds the sphere of
    radius ``margin * sqrt(3)`` around the origin (the ``[-1, 1]^3`` box)."""
    r = min(margin * math.sqrt(3.0) / radius, 1.0)
    return math.degrees(2.0 * math.asin(r))


def _res(res) -> Tuple[int, int]:
    if isinstance(res, (int, np.integer)):
        return int(res), int(res)
    w, h = res
    return int(w), int(h)


def _frame(up):
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    a = np.eye(3)[np.argmin(np.abs(u))]
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1), u


def fibonacci_cameras(n: int, radius: float = 4.0, res=256, fov: Optional[float] = None,
                      up=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0),
                      hemisphere: bool = False) -> List[View]:
    """``n`` cameras on a Fibonacci sphere of ``radius`` around ``target``, looking at it.

    The sphere's pole is ``up`` (also the cameras' up vector; at the poles another one is
    chosen, see :func:`look_at`).  ``hemisphere=True`` keeps to the ``up`` side.
    ``fov`` (horizontal, degrees) defaults to :func:`default_fov` (frames ``[-1, 1]^3``).
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    w, h = _res(res)
    fov = default_fov(radius) if fov is None else float(fov)
    i = np.arange(n) + 0.5
    z = 1.0 - i / n if hemisphere else 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    e1, e2, e3 = _frame(up)
    dirs = (r * np.cos(phi))[:, None] * e1 + (r * np.sin(phi))[:, None] * e2 + z[:, None] * e3
    t = np.asarray(target, np.float64)
    return [View.look_at(f"cam{i}", t + radius * d, t, up, w, h, fov_x=fov)
            for i, d in enumerate(dirs)]


def random_cameras(n: int, radius: float = 4.0, res=256, fov: Optional[float] = None,
                   seed: int = 0, up=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0),
                   hemisphere: bool = False) -> List[View]:
    """``n`` cameras at uniformly random points of a sphere (``numpy.random.default_rng(seed)``),
    looking at ``target``; arguments as :func:`fibonacci_cameras`."""
    w, h = _res(res)
    fov = default_fov(radius) if fov is None else float(fov)
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    if hemisphere:
        d = np.where((d @ u)[:, None] < 0, d - 2 * (d @ u)[:, None] * u, d)
    t = np.asarray(target, np.float64)
    return [View.look_at(f"cam{i}", t + radius * x, t, up, w, h, fov_x=fov)
            for i, x in enumerate(d)]


# ============================================================================ Dr.Jit
def _check_variant():
    if mi.variant() is None:
        raise RuntimeError("mi_tetvr.grid.volume: call mitsuba.set_variant(...) first "
                           "(e.g. 'llvm_ad_rgb' or 'cuda_ad_rgb')")


class TFEval:
    """A :class:`TransferFunction` evaluated exactly inside Dr.Jit.

    The piecewise-linear function with non-decreasing positions ``p`` and values ``v`` is
    written as the telescoping sum ``v_0 + sum_i (v_{i+1} - v_i) w_i(t)`` with
    ``w_i = clamp((t - p_i) / (p_{i+1} - p_i), 0, 1)`` (a step ``t >= p_i`` at a jump), which
    equals ``numpy.interp`` with clamping and the after-jump value at a jump.

    Parameters
    ----------
    tf : TransferFunction
    value_range : (lo, hi)
        Scalar values mapped to the TF's 0 and 1 (default ``(0, 1)``).
    opacity_scale : float
        Factor on the TF opacity (extinction per unit world length).
    """

    def __init__(self, tf: TransferFunction, value_range=(0.0, 1.0), opacity_scale=1.0):
        lo, hi = (float(x) for x in value_range)
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
            raise ValueError(f"value_range must be finite with lo <= hi, got {value_range!r}")
        s = float(opacity_scale)
        if not np.isfinite(s) or s < 0:
            raise ValueError(f"opacity_scale must be finite and >= 0, got {opacity_scale!r}")
        self.tf, self.lo, self.hi, self.opacity_scale = tf, lo, hi, s

    @staticmethod
    def _pl(t, pos, vals):
        out = float(vals[0])
        for i in range(len(pos) - 1):
            dv = float(vals[i + 1] - vals[i])
            if dv == 0.0:
                continue
            p0, p1 = float(pos[i]), float(pos[i + 1])
            if p1 > p0:
                w = dr.clip((t - p0) * (1.0 / (p1 - p0)), 0.0, 1.0)
            else:
                w = dr.select(t >= p0, 1.0, 0.0)
            out = out + dv * w
        return out

    def __call__(self, s):
        """Colour (Color3f, linear RGB) and extinction (Float) for scalar values ``s`` (Float)."""
        t = (s - self.lo) * (1.0 / (self.hi - self.lo)) if self.hi > self.lo else s * 0.0
        t = dr.clip(t, 0.0, 1.0)
        tf = self.tf
        c = mi.Color3f(*[mi.Float(0.0) + self._pl(t, tf.color_positions, tf.colors[:, k])
                         for k in range(3)])
        sigma = mi.Float(0.0) + self._pl(t, tf.opacity_positions, tf.opacities)
        return c, sigma * self.opacity_scale


class GridField:
    """A :class:`Volume`'s samples in a flat Dr.Jit buffer, with trilinear lookup.

    ``buffer`` (``mi.Float``, x fastest) may be replaced by a differentiable array.
    """

    def __init__(self, volume: Volume):
        _check_variant()
        nx, ny, nz = volume.shape
        self.shape = (nx, ny, nz)
        self.buffer = mi.Float(np.ascontiguousarray(volume.values, np.float32).ravel())
        self.origin = [float(v) for v in volume.origin]
        self.inv_spacing = [1.0 / float(v) for v in volume.spacing]
        lo, hi = volume.bounds()
        self.bbox = mi.ScalarBoundingBox3f(lo.tolist(), hi.tolist())

    def eval(self, p):
        """Trilinear interpolation at world points ``p`` (Point3f); clamps outside the box."""
        nx, ny, nz = self.shape
        g = [(p[a] - self.origin[a]) * self.inv_spacing[a] for a in range(3)]
        g = [dr.clip(g[a], 0.0, float(self.shape[a] - 1)) for a in range(3)]
        i0 = [dr.minimum(mi.Int32(dr.floor(g[a])), self.shape[a] - 2) for a in range(3)]
        f = [g[a] - mi.Float(i0[a]) for a in range(3)]
        base = i0[0] + nx * (i0[1] + ny * i0[2])
        sx, sy, sz = 1, nx, nx * ny
        b = self.buffer

        def v(o):
            return dr.gather(mi.Float, b, base + o)

        c00 = dr.lerp(v(0), v(sx), f[0])
        c10 = dr.lerp(v(sy), v(sy + sx), f[0])
        c01 = dr.lerp(v(sz), v(sz + sx), f[0])
        c11 = dr.lerp(v(sz + sy), v(sz + sy + sx), f[0])
        return dr.lerp(dr.lerp(c00, c10, f[1]), dr.lerp(c01, c11, f[1]), f[2])


@dr.syntax
def _march(field: GridField, tfe: TFEval, o, d, dt: float, min_transmittance: float):
    """The marching loop (see the module docstring for the model)."""
    bbox = mi.BoundingBox3f(mi.Point3f(field.bbox.min), mi.Point3f(field.bbox.max))
    hit, t0, t1 = bbox.ray_intersect(mi.Ray3f(o, d))
    t = dr.maximum(t0, 0.0)
    active = mi.Bool(hit) & (t1 > t)
    T = mi.Float(1.0)
    C = mi.Color3f(0.0)
    while dr.hint(active, label="volume_march"):
        h = dr.minimum(dt, t1 - t)
        s = field.eval(o + d * (t + 0.5 * h))
        c, sigma = tfe(s)
        a = dr.exp(-sigma * h)
        C += T * (1.0 - a) * c
        T *= a
        t += dt
        active &= (t < t1) & (T > min_transmittance)
    return C, 1.0 - T


def render_rays(field, tf, origins, directions, step: float = 0.25, value_range=(0.0, 1.0),
                opacity_scale: float = 1.0, min_transmittance: float = 1e-4):
    """March rays through a grid volume (the Dr.Jit core).

    Parameters
    ----------
    field : Volume or GridField
    tf : TransferFunction or TFEval
    origins, directions : Point3f / Vector3f, or (k, 3) arrays
        Ray origins and directions (normalised here).
    step : float
        Step length in voxels (times the smallest world spacing).
    value_range, opacity_scale
        See :class:`TFEval` (ignored when ``tf`` is already a ``TFEval``).
    min_transmittance : float
        Early termination threshold.

    Returns
    -------
    (Color3f, Float)
        Premultiplied linear RGB and alpha ``= 1 - T`` per ray.
    """
    _check_variant()
    if isinstance(field, Volume):
        field = GridField(field)
    if not isinstance(tf, TFEval):
        tf = TFEval(tf, value_range, opacity_scale)
    if step <= 0:
        raise ValueError(f"step must be > 0, got {step}")
    if not isinstance(origins, mi.Point3f):
        origins = mi.Point3f(*np.asarray(origins, np.float32).reshape(-1, 3).T)
    if not isinstance(directions, mi.Vector3f):
        directions = mi.Vector3f(*np.asarray(directions, np.float32).reshape(-1, 3).T)
    directions = dr.normalize(directions)
    dt = float(step) / max(field.inv_spacing)
    return _march(field, tf, origins, directions, dt, float(min_transmittance))


def camera_rays(camera):
    """Rays through the pixel centres of a :class:`~mi_tetvr.recon.datasets.View` or a Mitsuba
    sensor.

    Returns ``(origins Point3f, directions Vector3f, width, height)``, pixels in row-major
    order from the top-left.
    """
    _check_variant()
    if isinstance(camera, View):
        w, h = camera.width, camera.height
        idx = dr.arange(mi.UInt32, w * h)
        px, py = mi.Float(idx % w) + 0.5, mi.Float(idx // w) + 0.5
        # Mitsuba camera axes: +x to the image's left, +y up.
        x = (camera.cx - px) / camera.fx
        y = (camera.cy - py) / camera.fy
        m = np.asarray(camera.to_world, np.float64)
        R = [[float(m[r, c]) for c in range(3)] for r in range(3)]
        d = mi.Vector3f(R[0][0] * x + R[0][1] * y + R[0][2],
                        R[1][0] * x + R[1][1] * y + R[1][2],
                        R[2][0] * x + R[2][1] * y + R[2][2])
        o = mi.Point3f(*[float(v) for v in m[:3, 3]])
        o = dr.zeros(mi.Point3f, w * h) + o
        return o, dr.normalize(d), w, h
    sensor = camera
    w, h = (int(v) for v in sensor.film().size())
    idx = dr.arange(mi.UInt32, w * h)
    uv = mi.Point2f((mi.Float(idx % w) + 0.5) / w, (mi.Float(idx // w) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.0, uv, mi.Point2f(0.5, 0.5))
    return mi.Point3f(ray.o), mi.Vector3f(ray.d), w, h


def render_volume(volume, tf, camera, step: float = 0.25, value_range=(0.0, 1.0),
                  opacity_scale: float = 1.0, min_transmittance: float = 1e-4) -> np.ndarray:
    """Render a grid volume from one view.

    Parameters
    ----------
    volume : Volume or GridField
    tf : TransferFunction or TFEval
    camera : View or mitsuba Sensor (e.g. ``mi.load_dict(view.sensor_dict())``)
    step, value_range, opacity_scale, min_transmittance
        See :func:`render_rays`.

    Returns
    -------
    (height, width, 4) float32
        Premultiplied linear RGB and alpha.
    """
    o, d, w, h = camera_rays(camera)
    C, alpha = render_rays(volume, tf, o, d, step=step, value_range=value_range,
                           opacity_scale=opacity_scale, min_transmittance=min_transmittance)
    out = np.stack([np.asarray(C[0]), np.asarray(C[1]), np.asarray(C[2]),
                    np.asarray(alpha)], axis=-1)
    return out.reshape(h, w, 4).astype(np.float32)


# ============================================================================ data sets
def _tf_dict(tf: TransferFunction) -> dict:
    return {"colorspace": "linear",
            "color": [[float(p), *map(float, c)] for p, c in zip(tf.color_positions, tf.colors)],
            "opacity": [[float(p), float(a)] for p, a in zip(tf.opacity_positions, tf.opacities)]}


def make_dataset(volume: Volume, tf: TransferFunction, views: Union[int, Sequence[View]],
                 res=256, out_dir: PathType = "dataset",
                 test_views: Union[int, Sequence[View]] = 8, radius: float = 4.0,
                 fov: Optional[float] = None, seed: int = 0, step: float = 0.25,
                 value_range=(0.0, 1.0), opacity_scale: float = 1.0,
                 min_transmittance: float = 1e-4, up=(0.0, 0.0, 1.0),
                 progress: bool = True) -> dict:
    """Render train and test views of a grid volume into a NeRF-convention data set.

    Parameters
    ----------
    volume : Volume
    tf : TransferFunction
    views : int or list of View
        Training cameras, or their number (on a Fibonacci sphere, :func:`fibonacci_cameras`).
    res : int or (w, h)
        Image size for generated cameras.
    out_dir : path
        Receives ``transforms_train.json``, ``transforms_test.json``, ``volume_info.json``,
        ``train/r_<i>.png`` and ``test/r_<i>.png``.
    test_views : int or list of View
        Test cameras, or their number (uniformly random on the sphere, ``seed``).
    radius, fov, up
        Camera sphere radius, horizontal fov in degrees (default :func:`default_fov`), up.
    seed : int
        Seed of the random test cameras.
    step, value_range, opacity_scale, min_transmittance
        See :func:`render_rays`.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    dict
        ``"train"``, ``"test"``: (n, h, w, 4) float32 premultiplied linear RGBA renders;
        ``"cameras_train"``, ``"cameras_test"``: lists of :class:`View` (with their
        images); ``"out_dir"``.
    """
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(views, (int, np.integer)):
        views = fibonacci_cameras(int(views), radius, res, fov, up=up)
    if isinstance(test_views, (int, np.integer)):
        test_views = random_cameras(int(test_views), radius, res, fov, seed=seed, up=up) \
            if test_views > 0 else []
    field = GridField(volume)
    tfe = TFEval(tf, value_range, opacity_scale)
    result = {"out_dir": str(out)}
    bar = tqdm(total=len(views) + len(test_views), desc="render views", disable=not progress)
    posed = {}
    for split, cams in (("train", views), ("test", test_views)):
        posed[split] = []
        for i, cam in enumerate(cams):
            img = render_volume(field, tfe, cam, step=step, min_transmittance=min_transmittance)
            posed[split].append(dataclasses.replace(cam, name=f"r_{i}", image=img))
            bar.update(1)
        result[split] = (np.stack([p.image for p in posed[split]]) if cams
                         else np.zeros((0, 0, 0, 4), np.float32))
        result[f"cameras_{split}"] = posed[split]
    bar.close()
    write_nerf(Dataset(posed["train"], posed["test"]), out)
    info = {"volume": volume.info(), "transfer_function": _tf_dict(tf),
            "value_range": [float(v) for v in value_range],
            "opacity_scale": float(opacity_scale), "step_voxels": float(step),
            "step_world": float(step * float(np.min(volume.spacing))),
            "min_transmittance": float(min_transmittance),
            "model": "post-classification emission-absorption, midpoint rule, "
                     "premultiplied linear RGB over black, alpha = 1 - T",
            "png": "RGBA 8-bit, sRGB colour, straight alpha",
            "cameras": {"radius": float(radius), "fov_x_deg": float(views[0].fov_x) if views
                        else None, "up": [float(v) for v in up], "seed": int(seed),
                        "train": "fibonacci sphere" if views else None,
                        "n_train": len(views), "n_test": len(test_views),
                        "test": "uniform random on the sphere"}}
    with open(out / "volume_info.json", "w", encoding="utf-8") as f:
        json.dump(info, f, indent=2)
    return result
