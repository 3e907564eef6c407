"""One mesh file read into meshio's form: meshio first, VTK (through pyvista) for the
VTK formats meshio fails on, and its tets taken from the cells. What
:mod:`~mi_tetvr.mesh.io` (a tet mesh with its values) and
:mod:`~mi_tetvr.mesh.partition` (each piece of a partition) read files with."""
from __future__ import annotations

import contextlib
import io
import logging
import threading
import warnings
from pathlib import Path

import meshio
import numpy as np

from mi_tetvr.extras import needs
from mi_tetvr.mesh.topology import MeshError

__all__ = ["read_one_file", "tets_from_cells", "MeshError"]

#: Suffixes that VTK reads when meshio cannot.
_VTK_SUFFIXES = {".vtk", ".vtu", ".pvtu", ".vtkhdf", ".hdf", ".vtm"}
#: meshio cell types that are volume cells but not linear tets.
_OTHER_VOLUME_CELLS = {"hexahedron", "hexahedron20", "hexahedron27", "wedge", "wedge15",
                       "pyramid", "pyramid13", "polyhedron"}
_QUADRATIC_TETS = {"tetra10", "tetra20", "tetra35", "tetra56"}


def tets_from_cells(mesh: meshio.Mesh, path) -> np.ndarray:
    """(m, 4) tets of a meshio mesh: its tetra cells, higher-order tets
    linearized (with a warning); a :class:`MeshError` for no tets or other
    volume cells."""
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


#: ``sys.stdout``/``sys.stderr`` are process-wide: two threads that redirect
#: them at once (Mitsuba loads a scene's shapes in parallel) could each restore
#: the other's buffer and leave the process writing into it.
_REDIRECT = threading.Lock()


def _read_meshio(path) -> meshio.Mesh:
    """meshio's reading; what it printed becomes the error's reason (meshio
    exits with ``SystemExit`` on files it cannot parse)."""
    said = io.StringIO()
    try:
        with _REDIRECT, contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            return meshio.read(path)
    except (Exception, SystemExit) as e:
        text = " ".join(said.getvalue().split())
        raise MeshError(text or f"{type(e).__name__}: {e}") from None


class _Quiet(logging.Filter):
    """Drops the log records pyvista makes of VTK's errors (they become the
    exception's message instead)."""

    def filter(self, record):
        return False


def _read_vtk(path) -> meshio.Mesh:
    """VTK's reading (any VTK format), as a meshio mesh."""
    with needs("vis", "reading a VTK file meshio cannot read"):
        import pyvista as pv
    quiet, root = _Quiet(), logging.getLogger()
    root.addFilter(quiet)
    try:
        with pv.vtk_verbosity("off"), pv.VtkErrorCatcher() as caught, \
                warnings.catch_warnings():
            warnings.simplefilter("ignore")       # pyvista's own; VTK's errors are raised below
            try:
                data = pv.read(path)
            except Exception as e:
                reasons = [ev.alert.strip() for ev in caught.events][:1] or [str(e)]
                raise MeshError("; ".join(reasons)) from None
    finally:
        root.removeFilter(quiet)
    if isinstance(data, pv.MultiBlock):
        data = data.combine()
    if data is None or data.n_cells == 0:
        raise MeshError("no cells")
    return pv.to_meshio(data.cast_to_unstructured_grid())


def read_one_file(path) -> meshio.Mesh:
    """One mesh file as meshio holds it: meshio first, VTK for the VTK formats meshio
    fails on. Raises :class:`MeshError` with both reasons when neither reads it,
    ``FileNotFoundError`` when it does not exist."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        return _read_meshio(path)
    except MeshError as e:
        first = f"meshio: {e}"
    if path.suffix.lower() not in _VTK_SUFFIXES:
        raise MeshError(f"{path}: cannot read mesh ({first})")
    try:
        return _read_vtk(path)
    except MeshError as e:
        raise MeshError(f"{path}: cannot read mesh ({first}; VTK: {e})") from None
