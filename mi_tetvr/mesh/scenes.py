"""Meshes of the bundled XML scenes in ``scenes/`` (generated, not stored)."""
from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

from mi_tetvr.mesh.generate import blob_field, blob_mesh, grid_mesh
from mi_tetvr.mesh.io import write_tetmesh
from mi_tetvr.mesh.tetmesh import TetMesh

SCENES_DIR = Path(__file__).resolve().parents[2] / "scenes"


def make_scene_meshes(directory=None, force=False):
    """Write the meshes the scenes reference into ``directory/meshes``.

    Returns the list of paths written (existing files are kept unless ``force``).
    """
    out = Path(directory or SCENES_DIR) / "meshes"
    out.mkdir(parents=True, exist_ok=True)
    written = []

    def save(name, mesh):
        p = out / name
        if force or not p.exists():
            write_tetmesh(p, mesh)
            written.append(p)

    save("blob.vtu", blob_mesh(cells=24, jitter=0.15))
    # A scalar field only (no color/opacity), to be shaded by a transfer function.
    v, t = grid_mesh(20, jitter=0.1, seed=3)
    r = np.linalg.norm(v * [1.0, 1.3, 1.6], axis=1)
    p = out / "radial_scalar.vtu"
    if force or not p.exists():
        meshio.write(p, meshio.Mesh(v, [("tetra", t)],
                                    point_data={"density": np.cos(3.0 * r) * np.exp(-r)}))
        written.append(p)
    # A U-shaped (non-convex) mesh for re-entry.
    v, t = grid_mesh((12, 12, 4), jitter=0.1, seed=4)
    c = v[t].mean(1)
    t = t[~((np.abs(c[:, 0]) < 0.34) & (c[:, 1] > -0.3))]
    col, op = blob_field(v, 3.0)
    save("ushape.vtu", TetMesh(v, t, np.clip(0.2 + 0.8 * col, 0, 1), 0.6 + op))
    p = out.parent / "volumes" / "default.npy"
    if force or not p.exists():
        p.parent.mkdir(exist_ok=True)
        np.save(p, default_volume())
        written.append(p)
    return written


def scalar_mesh():
    """The path of the project's own scalar mesh (``scenes/meshes/radial_scalar.vtu``,
    point array ``density``), made first when absent (:func:`make_scene_meshes`)."""
    make_scene_meshes()
    return SCENES_DIR / "meshes" / "radial_scalar.vtu"


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
