"""Meshes of the bundled XML scenes in ``scenes/`` (generated, not stored)."""
from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

from .generate import blob_field, blob_mesh, grid_mesh
from .io import write_tetmesh
from .mesh import TetMesh

SCENES_DIR = Path(__file__).resolve().parents[1] / "scenes"


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
    return written
