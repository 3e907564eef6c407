"""Reading and writing tetrahedral meshes: meshio (.vtu, .vtk, .msh, .mesh,
...), with VTK (through pyvista) reading every VTK format meshio cannot
(legacy files with sections meshio misparses, string arrays, ...).

Per-vertex point data ``color`` (n, 3, linear RGB) and ``opacity`` (n,
extinction per unit length in the mesh's units) are read by default; other
names are selectable. A mesh with only a scalar field can be pre-shaded at
load with a :class:`~mi_tetvr.transfer.TransferFunction`. Missing attributes
get :data:`~mi_tetvr.mesh.DEFAULT_COLOR` and :data:`~mi_tetvr.mesh.DEFAULT_OPACITY`.
Per-cell arrays are kept as cell data, or averaged onto the vertices on
request (``cell_to_point``); meshes with folded or degenerate tets load with
``repair`` (:func:`~mi_tetvr.mesh.topology.repair_tets`).

Errors are exceptions (:class:`~mi_tetvr.mesh.topology.MeshError` for a file
that cannot be read as a tet mesh), never an exit.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import meshio
import numpy as np

from mi_tetvr.extras import needs
from mi_tetvr.mesh.meshfile import _QUADRATIC_TETS, MeshError, read_one_file, tets_from_cells
from mi_tetvr.mesh.partition import assemble, blocks_path, read_partition
from mi_tetvr.mesh.tetmesh import TetMesh
from mi_tetvr.mesh.topology import _preview, repair_tets
from mi_tetvr.transfer import TransferFunction, read_transfer_function

__all__ = ["read_tetmesh", "write_tetmesh", "read_mesh_file", "cell_to_point_data", "choose_scalar",
           "tets_from_cells"]

#: Formats whose meshio writer drops point data.
_GEOMETRY_ONLY = {".msh", ".mesh"}


def read_mesh_file(path) -> meshio.Mesh:
    """A mesh file as meshio holds it: meshio first, VTK for the VTK formats
    meshio fails on, a partition's pieces joined (``.pvtu`` written by
    :mod:`~mi_tetvr.mesh.partition`). Raises :class:`MeshError` with both reasons
    when neither reads it, ``FileNotFoundError`` when it does not exist."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    if path.suffix.lower() == ".pvtu" and blocks_path(path).is_file():
        # (written by ``partition``: its pieces joined, each tet once)
        return assemble(read_partition(path))
    return read_one_file(path)


def _numeric(arrays, where, path):
    """The numeric arrays of a dict; the others (strings) are dropped with a warning."""
    out, dropped = {}, []
    for k, a in arrays.items():
        a = np.asarray(a)
        if np.issubdtype(a.dtype, np.number) or a.dtype == bool:
            out[k] = a
        else:
            dropped.append(k)
    if dropped:
        warnings.warn(f"{path}: non-numeric {where} arrays {dropped} ignored", stacklevel=3)
    return out


def _tet_cell_data(mesh: meshio.Mesh, path):
    """Cell arrays restricted to the tet blocks, in the order of the tets."""
    keep = [i for i, b in enumerate(mesh.cells)
            if b.type == "tetra" or b.type in _QUADRATIC_TETS]
    out = {}
    for k, blocks in mesh.cell_data.items():
        parts = [np.asarray(blocks[i]) for i in keep]
        if parts and all(p.shape[1:] == parts[0].shape[1:] for p in parts):
            out[k] = np.concatenate(parts)
    return _numeric(out, "cell", path)


def cell_to_point_data(vertices, tets, cell_data):
    """Per-tet arrays averaged onto the vertices (each vertex: the mean over
    the tets around it), as VTK's ``vtkCellDataToPointData`` does (ParaView's
    Cell Data to Point Data). Returns a dict of (n, ...) arrays."""
    with needs("vis", "cell data to point data (VTK)"):
        import pyvista as pv
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: np.asarray(tets)},
                               np.asarray(vertices, np.float64))
    for k, a in cell_data.items():
        grid.cell_data[k] = np.asarray(a)
    converted = grid.cell_data_to_point_data()
    return {k: np.asarray(converted.point_data[k]) for k in cell_data}


def _cell_hint(cell_data):
    return (f"; cell arrays {sorted(cell_data)} become point arrays with cell_to_point"
            if cell_data else "")


def choose_scalar(point_data, scalar, path, cell_data=None, cells=False) -> str:
    """The name of the scalar array to classify: ``scalar``, or the only
    scalar array there is (a :class:`MeshError` names the candidates
    otherwise). Point arrays only, unless ``cells``: then a cell array (one
    value per tet) is one too (a point array of the same name wins; with no
    name, point arrays are looked at first)."""
    cd = cell_data or {}

    def scalars(data):
        return [k for k, v in data.items() if v.ndim == 1 or v.shape[1:] == (1,)]
    if scalar is None:
        cands = scalars(point_data) or (scalars(cd) if cells else [])
        if len(cands) != 1:
            listed = scalars(point_data) + (scalars(cd) if cells else [])
            raise MeshError(f"{path}: choose the scalar field to shade (scalar "
                            f"{'point or cell' if cells else 'point'} arrays: {listed}"
                            f"{'' if cells else _cell_hint(cd)})")
        return cands[0]
    if scalar in point_data or (cells and scalar in cd):
        return scalar
    raise MeshError(f"{path}: no {'point- or cell-data' if cells else 'point-data'} array "
                    f"'{scalar}' (point arrays: {sorted(point_data)}"
                    f"{f'; cell arrays: {sorted(cd)}' if cells else _cell_hint(cd)})")


def read_tetmesh(path, *, color: str | None = "color", opacity: str | None = "opacity",
                 scalar: str | None = None, transfer_function=None,
                 value_range=None, opacity_scale: float = 1.0, cell_to_point: bool = False,
                 repair: bool = False) -> TetMesh:
    """Read a tet mesh file.

    Parameters
    ----------
    path : str or Path
        Any volume format meshio reads.
    color, opacity : str or None
        Names of the point-data arrays holding color (n, 3) and opacity (n,);
        ``None`` for a mesh read for its other arrays (a scalar field): the
        defaults, without a warning.
    scalar : str, optional
        Point-data array to pre-shade with ``transfer_function`` (default: the
        only scalar array, if there is exactly one).
    transfer_function : TransferFunction or path, optional
        When given, color and opacity come from the scalar field.
    value_range : (2,) float, optional
        Scalar range mapped to [0, 1] (default: the field's min and max).
    opacity_scale : float
        Multiplies the transfer function's opacity (extinction per unit length).
    cell_to_point : bool
        Average every per-tet array onto the vertices (:func:`cell_to_point_data`),
        so that it can be colored, shaded or selected like point data; a point
        array of the same name wins. Default: cell arrays stay cell data.
    repair : bool
        Drop tets with a repeated vertex, duplicates, flat and folded tets
        (:func:`~mi_tetvr.mesh.topology.repair_tets`), with a warning that
        says which and what it did to the boundary. Default: such a mesh is
        refused with an error naming the tets.

    Raises
    ------
    FileNotFoundError
    MeshError
        A file neither meshio nor VTK reads (both reasons given), no tets,
        cells that are not tets, an unknown or ambiguous array name.
    """
    path = Path(path)
    if transfer_function is None:
        unused = [n for n, v in (("scalar", scalar), ("value_range", value_range),
                                 ("opacity_scale", None if opacity_scale == 1.0 else 1))
                  if v is not None]
        if unused:
            raise ValueError(f"{', '.join(unused)} given but no transfer function to map "
                             f"the scalar with: add one, or leave them out")
    mesh = read_mesh_file(path)
    tets = tets_from_cells(mesh, path)
    points = np.asarray(mesh.points, np.float64)[:, :3]
    pd = _numeric({k: np.asarray(v) for k, v in mesh.point_data.items()}, "point", path)
    cd = _tet_cell_data(mesh, path)
    if repair:
        keep, report = repair_tets(points, tets)
        if not keep.all():
            what = ", ".join(f"{len(report[k])} {k.replace('_', ' ')}" for k in
                             ("folded", "flat", "duplicate", "repeated_vertex") if report[k])
            b0, b1 = report["boundary_faces"]
            warnings.warn(f"{path}: repair dropped {np.count_nonzero(~keep)} of {len(tets)} "
                          f"tets ({what}; tets {_preview(np.flatnonzero(~keep))}); "
                          f"boundary faces {b0} -> {b1}", stacklevel=2)
            tets = tets[keep]
            cd = {k: a[keep] for k, a in cd.items()}
    if cell_to_point and cd:
        converted = cell_to_point_data(points, tets, cd)
        pd = {**converted, **pd}
        cd = {}
    col = pd.pop(color, None)
    opa = pd.pop(opacity, None)
    if transfer_function is not None:
        tf = transfer_function if isinstance(transfer_function, TransferFunction) \
            else read_transfer_function(transfer_function)
        scalar = choose_scalar(pd, scalar, path, cd)
        col, opa = tf.shade(pd[scalar].reshape(len(points)), value_range=value_range,
                            opacity_scale=opacity_scale)
    elif col is None and opa is None and pd and (color or opacity):
        warnings.warn(f"{path}: no '{color}'/'{opacity}' point data; using default color "
                      f"and opacity (point arrays: {sorted(pd)}; pass a transfer function "
                      "to shade one)", stacklevel=2)
    if col is not None and np.ndim(col) == 2 and np.shape(col)[1] == 4:
        col = np.asarray(col)[:, :3]
    return TetMesh(points, tets, col, opa, pd, cd)


def write_tetmesh(path, mesh: TetMesh, *, color: str | None = "color",
                  opacity: str | None = "opacity"):
    """Write a tet mesh with its color and opacity as point data (any format
    meshio writes; formats without point data keep only the geometry);
    ``color=None`` / ``opacity=None`` leave them out (a mesh whose point data
    says everything)."""
    pd = dict(mesh.point_data)
    if color is not None:
        pd[color] = np.asarray(mesh.color, dtype=np.float64)
    if opacity is not None:
        pd[opacity] = np.asarray(mesh.opacity, dtype=np.float64)
    out = meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)], point_data=pd,
                      cell_data={k: [np.asarray(a)] for k, a in mesh.cell_data.items()})
    path = Path(path)
    if path.suffix.lower() in _GEOMETRY_ONLY:
        warnings.warn(f"{path}: this format keeps only the geometry through meshio; "
                      "color and opacity are not written (use .vtu or .vtk)", stacklevel=2)
    meshio.write(path, out)
