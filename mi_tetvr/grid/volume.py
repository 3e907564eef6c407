"""Scalar volumes on regular grids: the :class:`Volume`, trilinear sampling, readers and writers.

A volume is the ground truth for reconstruction (its images under a transfer function,
rendered by :mod:`mi_tetvr.grid.marcher` and written as a data set by
:mod:`mi_tetvr.recon.synthetic`). Numpy only: works without a Mitsuba variant.

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
    :func:`make_volume` / :func:`load_volume` center the box at the origin and scale it
    uniformly so that its largest extent is 2, i.e. it lies in ``[-1, 1]^3`` and touches
    ``+-1`` along its longest axis; the voxel aspect ratio from the file's spacing is kept.
    Grid x, y, z are world x, y, z.
Normalisation
    Values are mapped to ``[0, 1]`` by ``(v - lo) / (hi - lo)`` with ``(lo, hi)`` the data
    range (default: ``(min, max)`` of the data; pass ``value_range=`` to fix it, e.g.
    ``(0, 255)`` for uint8) and clipped to ``[0, 1]``.  ``Volume.data_range`` records
    ``(lo, hi)``.
"""
from __future__ import annotations

import gzip
import re
import struct
import zlib
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Tuple, Union

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["Volume", "make_volume", "load_volume", "write_cvol", "write_mhd", "trilinear_numpy"]

PathType = Union[str, "PathLike[str]"]


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

    def sample_points(self) -> np.ndarray:
        """(nz * ny * nx, 3) world positions of the samples, in ``values``' order."""
        lo, _ = self.bounds()
        nx, ny, nz = self.shape
        z, y, x = np.meshgrid(*(np.arange(k) for k in (nz, ny, nx)), indexing="ij")
        return lo + np.stack([x, y, z], -1).reshape(-1, 3) * self.spacing

    def resampled(self, spacing: float) -> "Volume":
        """The trilinear field sampled on an isotropic grid of ``spacing`` (world
        units) from the box's low corner, as many samples per axis as fit in the box."""
        lo, hi = self.bounds()
        spacing = float(spacing)
        n = np.floor((hi - lo) / spacing * (1 + 1e-9)).astype(np.int64) + 1
        if np.any(n < 2):
            raise ValueError(f"spacing {spacing:g} leaves fewer than 2 samples on an axis of "
                             f"the box {lo} .. {hi}")
        x, y, z = (lo[a] + np.arange(n[a]) * spacing for a in range(3))
        zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
        values = self.sample(np.stack([xx, yy, zz], -1))
        return Volume(values=np.ascontiguousarray(values, np.float32), spacing=np.full(3, spacing),
                      origin=lo.copy(), data_range=self.data_range,
                      source=f"{self.source} resampled to {n[0]}x{n[1]}x{n[2]}",
                      source_spacing=self.source_spacing * spacing / self.spacing)

    def refined(self, factor: int) -> "Volume":
        """The cubic B-spline interpolant of the samples (scipy.ndimage, mirrored
        at the faces) sampled ``factor`` times finer: ``(n - 1) * factor + 1``
        samples per axis, every ``factor``-th one a sample of this volume. Values
        stay >= 0 where these are (the spline's overshoot is clipped)."""
        with needs("tomo", "refining a volume by its cubic B-spline"):
            from scipy import ndimage
        factor = int(factor)
        if factor < 1:
            raise ValueError(f"refinement factor {factor} must be a positive integer")
        n = np.array(self.values.shape)
        fine = ndimage.zoom(self.values.astype(np.float64), ((n - 1) * factor + 1) / n,
                            order=3, mode="mirror", grid_mode=False)
        if self.values.min() >= 0:
            fine = np.clip(fine, 0.0, None)
        return Volume(values=fine.astype(np.float32), spacing=self.spacing / factor,
                      origin=self.origin.copy(), data_range=self.data_range,
                      source=f"{self.source} refined {factor}x (cubic B-spline)",
                      source_spacing=self.source_spacing / factor)

    def isotropic(self, rtol: float = 1e-6) -> bool:
        """Whether the samples are equally spaced along x, y and z."""
        return bool(np.allclose(self.spacing, self.spacing[0], rtol=rtol, atol=0.0))

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
        raise ValueError(f"{str(path)!r}: unknown cvol data type {typ} "
                         "(0 uint8, 1 uint16, 2 float)")
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
    """Write an uncompressed DiffDVR ``.cvol`` (uint8, uint16 or float32
    ``values (nz, ny, nx)``)."""
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
    with needs("vis", "reading VTK image data"):
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


def _load_npy(path: Path) -> np.ndarray:
    """A ``.npy`` file's array of numbers, or a message naming the file (numpy's
    own, for a file that is not one, speaks of pickles)."""
    try:
        v = np.load(path)
    except (ValueError, EOFError):
        # a file without the .npy header reads as a pickle, which is refused
        raise ValueError(f"{str(path)!r}: not a numpy array file (what np.save writes of a "
                         f"3D array of numbers)") from None
    if not isinstance(v, np.ndarray) or not (np.issubdtype(v.dtype, np.number)
                                             or v.dtype == bool):
        raise ValueError(f"{str(path)!r}: holds {getattr(v, 'dtype', type(v).__name__)} "
                         f"values, not numbers")
    return v


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
        v, sp = _load_npy(path), np.ones(3)
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
