"""The bundled scenes: XML scenes and transfer functions that ship with the package
(``mi_tetvr/scenes/``), and the meshes and volume they use, generated, not stored.

:func:`make_scenes` writes them all into a folder (``mi-tetvr make-scenes -o DIR``;
by default ``scenes/`` in the current directory), where the XML scenes find their
meshes (``meshes/blob.vtu``) and transfer functions (``tf_radial.json``).
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import meshio
import numpy as np

from mi_tetvr.mesh.generate import blob_field, blob_mesh, grid_mesh
from mi_tetvr.mesh.io import write_tetmesh
from mi_tetvr.mesh.tetmesh import TetMesh
from mi_tetvr.transfer import BUNDLED
#: Where :func:`make_scenes` writes by default (relative to the current directory).
DEFAULT_DIR = Path("scenes")


def bundled(name: str) -> Path:
    """The path of a file that ships with the package (``"default.xml"``,
    ``"tf_default.json"``); ``FileNotFoundError`` naming those there are."""
    path = BUNDLED / name
    if not path.is_file():
        names = sorted(p.name for p in BUNDLED.iterdir() if p.suffix in (".xml", ".json"))
        raise FileNotFoundError(f"no bundled scene file '{name}' (there are: "
                                f"{', '.join(names)})")
    return path


def _write(path: Path, write) -> None:
    """``write(tmp)`` into a file beside ``path``, then moved onto it: a reader (another
    process making the same scenes) sees the whole file or none."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def make_scenes(directory=None, force=False):
    """Write the bundled scenes into ``directory`` (default :data:`DEFAULT_DIR`): the
    XML scenes and transfer functions (copied where they differ), the meshes they
    reference into ``directory/meshes`` and the default volume into
    ``directory/volumes`` (generated where absent, or always with ``force``).

    Returns the list of paths written.
    """
    root = Path(DEFAULT_DIR if directory is None else directory)
    out = root / "meshes"
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for src in sorted(BUNDLED.iterdir()):
        dst = root / src.name
        if src.suffix in (".xml", ".json") and (
                not dst.is_file() or dst.read_bytes() != src.read_bytes()):
            _write(dst, lambda tmp, src=src: shutil.copyfile(src, tmp))
            written.append(dst)

    def save(name, make):
        p = out / name
        if force or not p.exists():
            _write(p, make)
            written.append(p)

    save("blob.vtu", lambda p: write_tetmesh(p, blob_mesh(cells=24, jitter=0.15)))

    def radial(p):
        # A scalar field only (no color/opacity), to be shaded by a transfer function.
        v, t = grid_mesh(20, jitter=0.1, seed=3)
        r = np.linalg.norm(v * [1.0, 1.3, 1.6], axis=1)
        meshio.write(p, meshio.Mesh(v, [("tetra", t)],
                                    point_data={"density": np.cos(3.0 * r) * np.exp(-r)}))
    save("radial_scalar.vtu", radial)

    def ushape(p):
        # A U-shaped (non-convex) mesh for re-entry.
        v, t = grid_mesh((12, 12, 4), jitter=0.1, seed=4)
        c = v[t].mean(1)
        t = t[~((np.abs(c[:, 0]) < 0.34) & (c[:, 1] > -0.3))]
        col, op = blob_field(v, 3.0)
        write_tetmesh(p, TetMesh(v, t, np.clip(0.2 + 0.8 * col, 0, 1), 0.6 + op))
    save("ushape.vtu", ushape)
    p = root / "volumes" / "default.npy"
    if force or not p.exists():
        p.parent.mkdir(exist_ok=True)
        _write(p, lambda tmp: np.save(tmp, default_volume()))
        written.append(p)
    return written


def scalar_mesh(directory=None):
    """The path of the project's own scalar mesh (``meshes/radial_scalar.vtu`` of the
    scenes in ``directory``, default :data:`DEFAULT_DIR`; point array ``density``),
    made first when absent (:func:`make_scenes`)."""
    root = Path(DEFAULT_DIR if directory is None else directory)
    make_scenes(root)
    return root / "meshes" / "radial_scalar.vtu"


def default_volume(n=64):
    """The project's own scalar volume (n^3, values in [0, 1], x fastest as
    ``values[z, y, x]``): a tilted ring, three blobs and a faint shell, the
    default data set's ground truth (shaded by ``scenes/tf_default.json``)."""
    x = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    z, y, x = np.meshgrid(x, x, x, indexing="ij")
    p = np.stack([x, y, z], -1)
    c, s = np.cos(0.5), np.sin(0.5)
    q = p @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])  # tilted ring in the xy plane
    ring = np.exp(-((np.hypot(q[..., 0], q[..., 1]) - 0.55) ** 2 + q[..., 2] ** 2) / 0.012)
    blobs = sum(a * np.exp(-np.sum((p - np.array(m)) ** 2, -1) / w) for a, m, w in (
        (1.0, (0.0, 0.0, 0.0), 0.03), (0.9, (0.35, -0.45, 0.3), 0.015),
        (0.8, (-0.4, 0.35, -0.35), 0.02)))
    shell = 0.25 * np.exp(-(np.linalg.norm(p, axis=-1) - 0.85) ** 2 / 0.004)
    return np.clip(0.6 * ring + blobs + shell, 0.0, 1.0).astype(np.float32)
