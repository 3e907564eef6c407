"""Partitioned meshes as ParaView has them: a k-d split of space into boxes,
one ``.vtu`` piece per box, a ``.pvtu`` that names the pieces.

Space is split into ``N`` boxes by a k-d tree over the tet centroids (each
split at the centroids' quantile along the longest axis of the current set;
``N`` need not be a power of two). The outermost boxes reach to infinity, so
the boxes tile all of space and every ray is cut into one interval per box.
A piece holds every tet whose bounding box touches its box: a tet on a
boundary is in every block it touches, owned by the block that holds its
centroid and marked as VTK's duplicate cell (``vtkGhostType`` 1) in the
others, so ParaView opens the ``.pvtu`` as the mesh once over. Each piece
keeps the whole mesh's indices of its points and cells (``GlobalPointIds``,
``GlobalCellIds``, as ParaView's *RedistributeDataSet* names them).

The boxes, the whole mesh's bounds and the ranges of its arrays are written
beside the ``.pvtu`` (``NAME.blocks.json``): a renderer of one block reads
its piece and that file, never the whole mesh.

Rendering a block clipped to its box integrates the tets of the whole mesh
over that part of each ray (a tet cut by the box is integrated over the part
inside, the field being linear in it), and boxes are convex and disjoint:
compositing the blocks front to back in the order a ray enters their boxes
is the whole mesh's image (:mod:`mi_tetvr.distributed`).
"""
from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_tetvr.mesh.meshfile import read_one_file, tets_from_cells
from mi_tetvr.mesh.topology import MeshError

#: Point and cell arrays of a piece that hold the whole mesh's indices.
GLOBAL_POINT_IDS, GLOBAL_CELL_IDS = "GlobalPointIds", "GlobalCellIds"
#: VTK's ghost array and its flag for a cell owned by another piece.
GHOST, DUPLICATE_CELL = "vtkGhostType", 1
#: Arrays the partition adds to each piece (not the mesh's own data).
PIECE_ARRAYS = (GLOBAL_POINT_IDS, GLOBAL_CELL_IDS, GHOST)
#: The file beside ``NAME.pvtu`` that describes its blocks.
BLOCKS_SUFFIX = ".blocks.json"
FORMAT = "mi_tetvr partition 1"

_VTK_TYPES = {"float32": "Float32", "float64": "Float64", "int8": "Int8", "uint8": "UInt8",
              "int16": "Int16", "uint16": "UInt16", "int32": "Int32", "uint32": "UInt32",
              "int64": "Int64", "uint64": "UInt64"}


@dataclass
class Block:
    """One block: its box (``lo``, ``hi``; infinite where it reaches out of
    the mesh), its piece's file and sizes."""
    lo: np.ndarray
    hi: np.ndarray
    piece: str = ""
    tets: int = 0
    owned: int = 0
    vertices: int = 0

    def to_json(self):
        # (JSON has no infinity: an open side is null)
        box = [[float(x) if np.isfinite(x) else None for x in b] for b in (self.lo, self.hi)]
        return {"piece": self.piece, "box": box, "tets": self.tets, "owned": self.owned,
                "vertices": self.vertices}

    @classmethod
    def from_json(cls, d):
        lo, hi = (np.array([sign * np.inf if x is None else float(x) for x in b], np.float64)
                  for sign, b in zip((-1, 1), d["box"]))
        return cls(lo, hi, d["piece"], int(d["tets"]), int(d["owned"]), int(d["vertices"]))


@dataclass
class Partition:
    """A partitioned mesh as :func:`read_partition` finds it: the ``.pvtu``,
    its blocks in the k-d order, and the whole mesh's size, bounds and the
    ranges of its point and cell arrays (``{name: [min, max]}``)."""
    path: Path
    blocks: list
    vertices: int
    tets: int
    bounds: np.ndarray
    point_ranges: dict
    cell_ranges: dict

    def piece_path(self, k) -> Path:
        return self.path.parent / self.blocks[k].piece

    def boxes(self):
        """(N, 2, 3) the blocks' boxes, +-inf where a box is open."""
        return np.stack([np.stack([b.lo, b.hi]) for b in self.blocks])


def kd_boxes(centroids, n) -> np.ndarray:
    """(n, 2, 3) boxes tiling space: a k-d split of ``centroids`` (m, 3) into
    ``n`` groups of near equal size (the longest axis of each group's extent,
    at the quantile that gives its two halves ``n // 2`` and ``n - n // 2``
    blocks); open to infinity outside."""
    c = np.asarray(centroids, np.float64)
    if n < 1:
        raise ValueError(f"the number of blocks must be at least 1, got {n}")
    if len(c) < n:
        raise ValueError(f"cannot split {len(c)} tets into {n} blocks")
    root = np.array([[-np.inf] * 3, [np.inf] * 3])
    out = []

    def split(box, idx, k):
        if k == 1:
            out.append(box)
            return
        pts = c[idx]
        axis = int(np.argmax(pts.max(0) - pts.min(0)))
        left = k // 2
        rank = (len(idx) * left) // k
        order = np.argpartition(pts[:, axis], rank)
        value = float(pts[order[rank], axis])
        lbox, rbox = box.copy(), box.copy()
        lbox[1, axis] = value
        rbox[0, axis] = value
        split(lbox, idx[order[:rank]], left)
        split(rbox, idx[order[rank:]], k - left)

    split(root, np.arange(len(c)), int(n))
    return np.stack(out)


def block_members(vertices, tets, box):
    """``(touching, owned)``: boolean masks of the tets whose bounding box
    touches ``box`` (2, 3) and of those whose centroid lies in it (the box
    half-open, ``lo <= c < hi``, so that each tet has one owner)."""
    corners = vertices[tets]                     # (m, 4, 3)
    tmin, tmax = corners.min(1), corners.max(1)
    lo, hi = box
    touching = np.all(tmax >= lo, 1) & np.all(tmin <= hi, 1)
    c = corners.mean(1)
    owned = np.all(c >= lo, 1) & np.all(c < hi, 1)
    return touching, owned


def partition_mesh(vertices, tets, out, blocks: int, point_data=None, cell_data=None, *,
                   progress=None) -> Partition:
    """Write the mesh ``vertices`` (n, 3), ``tets`` (m, 4) with its
    ``point_data`` and ``cell_data`` (dicts of arrays) as ``out`` (``.pvtu``)
    and ``blocks`` pieces beside it (``<stem>/<stem>_<k>.vtu``), with
    ``<stem>.blocks.json``. ``progress``: a callable given each piece's
    index once written."""
    import meshio
    out = Path(out)
    if out.suffix.lower() != ".pvtu":
        raise ValueError(f"a partitioned mesh is written as .pvtu, got {out}")
    vertices = np.asarray(vertices, np.float64)
    tets = np.asarray(tets, np.int64)
    point_data = {k: np.asarray(v) for k, v in (point_data or {}).items()}
    cell_data = {k: np.asarray(v) for k, v in (cell_data or {}).items()}
    for name in PIECE_ARRAYS:
        if name in point_data or name in cell_data:
            raise ValueError(f"the mesh already has an array named '{name}': it is partitioned")
    centroids = vertices[tets].mean(1)
    boxes = kd_boxes(centroids, blocks)
    folder = out.parent / out.stem
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for k, box in enumerate(boxes):
        touching, owned = block_members(vertices, tets, box)
        cells = np.flatnonzero(touching)
        piece_tets = tets[cells]
        used = np.zeros(len(vertices), bool)
        used[piece_tets.ravel()] = True
        ids = np.flatnonzero(used)
        local = np.full(len(vertices), -1, np.int64)
        local[ids] = np.arange(len(ids))
        pd = {name: a[ids] for name, a in point_data.items()}
        pd[GLOBAL_POINT_IDS] = ids.astype(np.int64)
        cd = {name: [a[cells]] for name, a in cell_data.items()}
        cd[GLOBAL_CELL_IDS] = [cells.astype(np.int64)]
        cd[GHOST] = [np.where(owned[cells], 0, DUPLICATE_CELL).astype(np.uint8)]
        name = f"{out.stem}/{out.stem}_{k}.vtu"
        meshio.write(out.parent / name, meshio.Mesh(vertices[ids], [("tetra", local[piece_tets])],
                                                    point_data=pd, cell_data=cd))
        written.append(Block(box[0], box[1], name, len(cells), int(owned[cells].sum()),
                             len(ids)))
        if progress is not None:
            progress(k)
    if sum(b.owned for b in written) != len(tets):
        raise AssertionError("the blocks do not own every tet once")
    _write_pvtu(out, [b.piece for b in written], point_data, cell_data)
    part = Partition(out, written, len(vertices), len(tets),
                     np.stack([vertices.min(0), vertices.max(0)]),
                     _ranges(point_data), _ranges(cell_data))
    _write_blocks(part)
    return part


def _ranges(data):
    return {k: [float(np.min(v)), float(np.max(v))] for k, v in data.items()
            if np.size(v) and np.issubdtype(np.asarray(v).dtype, np.number)}


def _pdata_array(name, a):
    """The attributes of a ``PDataArray`` declaring array ``a`` (its name, if any)."""
    a = np.asarray(a)
    comps = 1 if a.ndim == 1 else int(np.prod(a.shape[1:]))
    return {"type": _VTK_TYPES[a.dtype.name], **({"Name": name} if name is not None else {}),
            "NumberOfComponents": str(comps)}


def _write_pvtu(out, pieces, point_data, cell_data):
    """The ``.pvtu`` naming the pieces and declaring their arrays (as VTK's
    ``vtkXMLPUnstructuredGridWriter`` writes it)."""
    root = ET.Element("VTKFile", type="PUnstructuredGrid", version="1.0",
                      byte_order="LittleEndian", header_type="UInt64")
    grid = ET.SubElement(root, "PUnstructuredGrid", GhostLevel="1")
    ppd = ET.SubElement(grid, "PPointData")
    for name, a in {**point_data, GLOBAL_POINT_IDS: np.zeros(1, np.int64)}.items():
        ET.SubElement(ppd, "PDataArray", _pdata_array(name, a))
    pcd = ET.SubElement(grid, "PCellData")
    for name, a in {**cell_data, GLOBAL_CELL_IDS: np.zeros(1, np.int64),
                    GHOST: np.zeros(1, np.uint8)}.items():
        ET.SubElement(pcd, "PDataArray", _pdata_array(name, a))
    pp = ET.SubElement(grid, "PPoints")
    ET.SubElement(pp, "PDataArray", _pdata_array(None, np.zeros((1, 3))))
    for piece in pieces:
        ET.SubElement(grid, "Piece", Source=piece)
    ET.indent(root)
    ET.ElementTree(root).write(out, xml_declaration=True, encoding="utf-8")


def blocks_path(pvtu) -> Path:
    pvtu = Path(pvtu)
    return pvtu.with_name(pvtu.stem + BLOCKS_SUFFIX)


def _write_blocks(part: Partition):
    d = {"format": FORMAT, "vertices": part.vertices, "tets": part.tets,
         "bounds": part.bounds.tolist(), "point_ranges": part.point_ranges,
         "cell_ranges": part.cell_ranges, "blocks": [b.to_json() for b in part.blocks]}
    blocks_path(part.path).write_text(json.dumps(d, indent=1))


def read_partition(pvtu) -> Partition:
    """The blocks of a ``.pvtu`` written by :func:`partition_mesh`. Raises
    ``FileNotFoundError`` (the file, its ``.blocks.json`` or a piece is
    missing) or :class:`MeshError` (a ``.pvtu`` whose pieces do not match
    its blocks)."""
    pvtu = Path(pvtu)
    if not pvtu.is_file():
        raise FileNotFoundError(f"partitioned mesh not found: {pvtu}")
    side = blocks_path(pvtu)
    if not side.is_file():
        raise MeshError(f"{pvtu}: no {side.name} beside it: its blocks' boxes are unknown "
                        f"(write it with `mi-tetvr partition MESH -o {pvtu.name} --blocks N`)")
    try:
        d = json.loads(side.read_text())
        if d.get("format") != FORMAT:
            raise ValueError(f"format {d.get('format')!r}, not {FORMAT!r}")
        blocks = [Block.from_json(b) for b in d["blocks"]]
        part = Partition(pvtu, blocks, int(d["vertices"]), int(d["tets"]),
                         np.asarray(d["bounds"], np.float64), d["point_ranges"],
                         d["cell_ranges"])
    except (ValueError, KeyError, TypeError) as e:
        raise MeshError(f"{side}: cannot read the blocks ({e})") from None
    try:
        sources = [p.get("Source") for p in ET.parse(pvtu).getroot().iter("Piece")]
    except ET.ParseError as e:
        raise MeshError(f"{pvtu}: cannot read it ({e})") from None
    if sources != [b.piece for b in blocks]:
        raise MeshError(f"{pvtu}: its pieces {sources} are not the blocks of {side.name} "
                        f"({[b.piece for b in blocks]})")
    missing = [str(part.piece_path(k)) for k in range(len(blocks))
               if not part.piece_path(k).is_file()]
    if missing:
        raise FileNotFoundError(f"{pvtu}: {len(missing)} of {len(blocks)} pieces missing: "
                                f"{', '.join(missing)}")
    return part


def read_piece(part: Partition, k, *, ghosts=False):
    """``(vertices, tets, point_data, cell_data, global_point_ids)`` of block
    ``k``'s piece: its own arrays, the partition's taken out; ``ghosts``:
    also ``(global cell ids, owned)`` of its tets."""
    path = part.piece_path(k)
    m = read_one_file(path)
    tets = tets_from_cells(m, path)
    pd = {k_: np.asarray(v) for k_, v in m.point_data.items()}
    cd = {k_: np.concatenate([np.asarray(b) for b in v]) for k_, v in m.cell_data.items()}
    missing = [n for n, d in ((GLOBAL_POINT_IDS, pd), (GLOBAL_CELL_IDS, cd), (GHOST, cd))
               if n not in d]
    if missing:
        raise MeshError(f"{path}: no {missing} arrays: not a piece of {part.path.name}")
    ids = pd.pop(GLOBAL_POINT_IDS).astype(np.int64).reshape(-1)
    cells, owned = cd.pop(GLOBAL_CELL_IDS).astype(np.int64), cd.pop(GHOST) == 0
    out = (np.asarray(m.points, np.float64)[:, :3], tets, pd, cd, ids)
    return out + ((cells, owned),) if ghosts else out


def assemble(part: Partition):
    """The whole mesh from its pieces (a meshio mesh: the points by their
    global ids, each tet once, in the original order)."""
    import meshio
    points = np.zeros((part.vertices, 3))
    tets = np.zeros((part.tets, 4), np.int64)
    point_data, cell_data = {}, {}
    for k in range(len(part.blocks)):
        v, t, pd, cd, ids, (cells, own) = read_piece(part, k, ghosts=True)
        points[ids] = v
        tets[cells[own]] = ids[t[own]]
        for n, a in pd.items():
            point_data.setdefault(n, np.zeros((part.vertices,) + a.shape[1:], a.dtype))[ids] = a
        for n, a in cd.items():
            cell_data.setdefault(n, np.zeros((part.tets,) + a.shape[1:], a.dtype))[cells[own]] \
                = a[own]
    return meshio.Mesh(points, [("tetra", tets)], point_data=point_data,
                       cell_data={n: [a] for n, a in cell_data.items()})


def grid_blocks(shape, n):
    """``n`` k-d blocks of a grid of ``shape`` cells: (n, 2, 3) cell-index
    ranges ``[c0, c1)``, split as :func:`kd_boxes` splits (the longest axis,
    ``n // 2`` blocks to the lower part)."""
    out = []

    def split(c0, c1, k):
        if k == 1:
            out.append(np.stack([c0, c1]))
            return
        axis = int(np.argmax(c1 - c0))
        left = k // 2
        cut = c0[axis] + ((c1[axis] - c0[axis]) * left) // k
        if not c0[axis] < cut < c1[axis]:
            raise ValueError(f"cannot split a grid of {tuple(shape)} cells into {n} blocks")
        lc1, rc0 = c1.copy(), c0.copy()
        lc1[axis] = cut
        rc0[axis] = cut
        split(c0, lc1, left)
        split(rc0, c1, k - left)

    split(np.zeros(3, np.int64), np.asarray(shape, np.int64), int(n))
    return np.stack(out)


def write_grid_partition(shape, out, blocks: int, fields, lo=(-1.0, -1.0, -1.0),
                         hi=(1.0, 1.0, 1.0), *, progress=None) -> Partition:
    """The regular tet grid :func:`~mi_tetvr.mesh.generate.grid_mesh` of
    ``shape`` cells (6 tets each) partitioned into ``blocks`` as
    :func:`partition_mesh` would, written block by block: the whole mesh is
    never held (a mesh larger than memory). ``fields(points)`` gives the point
    arrays of points (k, 3): a dict of (k, ...) arrays. The boxes are the
    grid's planes between blocks; each piece holds its cells and the layer of
    cells around them (whose tets touch its box: ghosts)."""
    import meshio
    from mi_tetvr.mesh.generate import KUHN_TETS
    out = Path(out)
    if out.suffix.lower() != ".pvtu":
        raise ValueError(f"a partitioned mesh is written as .pvtu, got {out}")
    shape = np.asarray(shape, np.int64)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    h = (hi - lo) / shape
    ranges = grid_blocks(shape, blocks)
    folder = out.parent / out.stem
    folder.mkdir(parents=True, exist_ok=True)
    npts = shape + 1
    written, ranges_of = [], {}
    point_example = None
    for k, (c0, c1) in enumerate(ranges):
        a0, a1 = np.maximum(c0 - 1, 0), np.minimum(c1 + 1, shape)    # with the ghost layer
        # the piece's points: the global grid points of cells a0..a1
        pidx = [np.arange(a0[i], a1[i] + 1) for i in range(3)]
        gi, gj, gk = np.meshgrid(*pidx, indexing="ij")
        ids = ((gi * npts[1] + gj) * npts[2] + gk).ravel()
        points = np.stack([lo[i] + [gi, gj, gk][i].ravel() * h[i] for i in range(3)], 1)
        # its cells' tets in the piece's own point numbering (x slowest, as grid_tets)
        m = a1 - a0
        local = np.arange(len(ids)).reshape(*(m + 1))
        corners = np.stack([local[i:i + m[0], j:j + m[1], kk:kk + m[2]].ravel()
                            for i in (0, 1) for j in (0, 1) for kk in (0, 1)], 1)
        tets = corners[:, KUHN_TETS].reshape(-1, 4)
        ci, cj, ck = np.meshgrid(*[np.arange(a0[i], a1[i]) for i in range(3)], indexing="ij")
        cell = ((ci * shape[1] + cj) * shape[2] + ck).ravel()
        gcells = (cell[:, None] * 6 + np.arange(6)).ravel()
        inside = np.all([(c >= c0[i]) & (c < c1[i]) for i, c in
                         enumerate((ci.ravel(), cj.ravel(), ck.ravel()))], 0)
        owned = np.repeat(inside, 6)
        pd = {name: np.asarray(v) for name, v in fields(points).items()}
        point_example = point_example or pd
        for name, v in pd.items():
            r = ranges_of.setdefault(name, [np.inf, -np.inf])
            r[0], r[1] = min(r[0], float(v.min())), max(r[1], float(v.max()))
        pd[GLOBAL_POINT_IDS] = ids
        name = f"{out.stem}/{out.stem}_{k}.vtu"
        meshio.write(out.parent / name, meshio.Mesh(points, [("tetra", tets)], point_data=pd,
                                                    cell_data={GLOBAL_CELL_IDS: [gcells],
                                                               GHOST: [np.where(owned, 0, 1)
                                                                       .astype(np.uint8)]}),
                     compression=None)
        box = np.stack([np.where(c0 > 0, lo + c0 * h, -np.inf),
                        np.where(c1 < shape, lo + c1 * h, np.inf)])
        written.append(Block(box[0], box[1], name, len(tets), int(owned.sum()), len(ids)))
        del points, tets, pd, corners, gcells, owned
        if progress is not None:
            progress(k)
    _write_pvtu(out, [b.piece for b in written], point_example, {})
    part = Partition(out, written, int(np.prod(npts)), int(6 * np.prod(shape)),
                     np.stack([lo, hi]), ranges_of, {})
    _write_blocks(part)
    return part
