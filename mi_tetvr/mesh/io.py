"""Reading and writing tetrahedral meshes with meshio (.vtu, .vtk, .msh, .mesh, ...).

Per-vertex point data ``color`` (n, 3, linear RGB) and ``opacity`` (n,
extinction per unit length in the mesh's units) are read by default; other
names are selectable. A mesh with only a scalar field can be pre-shaded at
load with a :class:`~mi_tetvr.transfer.TransferFunction`. Missing attributes
get :data:`~mi_tetvr.mesh.DEFAULT_COLOR` and :data:`~mi_tetvr.mesh.DEFAULT_OPACITY`.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import meshio
import numpy as np

from mi_tetvr.mesh.tetmesh import TetMesh
from mi_tetvr.mesh.topology import MeshError
from mi_tetvr.transfer import TransferFunction, read_transfer_function

#: meshio cell types that are volume cells but not linear tets.
_OTHER_VOLUME_CELLS = {"hexahedron", "hexahedron20", "hexahedron27", "wedge", "wedge15",
                       "pyramid", "pyramid13", "polyhedron"}
#: Formats whose meshio writer drops point data.
_GEOMETRY_ONLY = {".msh", ".mesh"}
_QUADRATIC_TETS = {"tetra10", "tetra20", "tetra35", "tetra56"}


def _tets_from_cells(mesh: meshio.Mesh, path) -> np.ndarray:
    tets = []
    for block in mesh.cells:
        if block.type == "tetra":
            tets.append(block.data)
        elif block.type in _QUADRATIC_TETS:
            warnings.warn(f"{path}: {len(block.data)} higher-order '{block.type}' cells "
                          "linearized (corner vertices kept, mid-edge nodes ignored)",
                          stacklevel=3)
            tets.append(block.data[:, :4])
        elif block.type in _OTHER_VOLUME_CELLS or block.type.startswith("hexahedron"):
            raise MeshError(f"{path}: contains {len(block.data)} '{block.type}' cells; only "
                            "tetrahedra are supported (tetrahedralize the mesh first)")
        # surface, line and vertex cells (boundary markers) are ignored
    if not tets:
        raise MeshError(f"{path}: no tetrahedral cells found "
                        f"(cell types: {[b.type for b in mesh.cells]})")
    return np.concatenate(tets).astype(np.int64)


def read_tetmesh(path, *, color: str = "color", opacity: str = "opacity",
                 scalar: str | None = None, transfer_function=None,
                 value_range=None, opacity_scale: float = 1.0) -> TetMesh:
    """Read a tet mesh file.

    Parameters
    ----------
    path : str or Path
        Any volume format meshio reads.
    color, opacity : str
        Names of the point-data arrays holding color (n, 3) and opacity (n,).
    scalar : str, optional
        Point-data array to pre-shade with ``transfer_function`` (default: the
        only scalar array, if there is exactly one).
    transfer_function : TransferFunction or path, optional
        When given, color and opacity come from the scalar field.
    value_range : (2,) float, optional
        Scalar range mapped to [0, 1] (default: the field's min and max).
    opacity_scale : float
        Multiplies the transfer function's opacity (extinction per unit length).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        mesh = meshio.read(path)
    except Exception as e:  # meshio raises many types; name the file
        raise MeshError(f"{path}: cannot read mesh ({type(e).__name__}: {e})") from e
    tets = _tets_from_cells(mesh, path)
    pd = {k: np.asarray(v) for k, v in mesh.point_data.items()}
    col = pd.pop(color, None)
    opa = pd.pop(opacity, None)
    if transfer_function is not None:
        tf = transfer_function if isinstance(transfer_function, TransferFunction) \
            else read_transfer_function(transfer_function)
        if scalar is None:
            cands = [k for k, v in pd.items() if v.ndim == 1 or v.shape[1:] == (1,)]
            if len(cands) != 1:
                raise MeshError(f"{path}: choose the scalar field to shade "
                                f"(scalar point arrays: {cands})")
            scalar = cands[0]
        if scalar not in pd:
            raise MeshError(f"{path}: no point-data array '{scalar}' "
                            f"(available: {sorted(pd)})")
        col, opa = tf.shade(pd[scalar].reshape(len(mesh.points)), value_range=value_range,
                            opacity_scale=opacity_scale)
    elif col is None and opa is None and pd:
        warnings.warn(f"{path}: no '{color}'/'{opacity}' point data; using default color "
                      f"and opacity (point arrays: {sorted(pd)}; pass a transfer function "
                      "to shade one)", stacklevel=2)
    if col is not None and np.ndim(col) == 2 and np.shape(col)[1] == 4:
        col = np.asarray(col)[:, :3]
    return TetMesh(mesh.points[:, :3], tets, col, opa, pd)


def write_tetmesh(path, mesh: TetMesh, *, color: str = "color", opacity: str = "opacity"):
    """Write a tet mesh with its color and opacity as point data (any format
    meshio writes; formats without point data keep only the geometry)."""
    pd = dict(mesh.point_data)
    pd[color] = np.asarray(mesh.color, dtype=np.float64)
    pd[opacity] = np.asarray(mesh.opacity, dtype=np.float64)
    out = meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)], point_data=pd)
    path = Path(path)
    if path.suffix.lower() in _GEOMETRY_ONLY:
        warnings.warn(f"{path}: this format keeps only the geometry through meshio; "
                      "color and opacity are not written (use .vtu or .vtk)", stacklevel=2)
    meshio.write(path, out)
