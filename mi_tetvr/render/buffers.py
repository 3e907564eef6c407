"""The flat buffers the walk reads, and the one encoding of neighbour links.

A *link* names a face of a tet from the side of the tet it belongs to:
``4 * tet + local_face`` (:func:`pack_links`, :func:`unpack_link`), ``-1``
where there is nothing across (the mesh boundary). Local face ``f`` is the
face opposite local vertex ``f`` (:data:`mi_tetvr.mesh.topology.FACES`).

The ``tetmesh`` shape packs its topology into per-shape index arrays
(:func:`shape_index_arrays`, numpy, local indices); the integrator
concatenates the shapes of a scene into one :class:`MeshBuffers`
(:func:`index_buffers`, global indices) and pairs it with the optical model's
parameters in a :class:`TetGroup`. A tet's record is one 32-byte cell: its
four corners and its four links, so that a step of the walk reads one cache
line of the tets (:func:`tets_of`, :func:`links_of` read them in numpy).
"""
from __future__ import annotations

import functools
import importlib
from typing import TYPE_CHECKING, Any

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.mesh.topology import Topology, chunk_slices
from mi_tetvr.render.pytree import from_scalar_leaves, scalar_leaves
from mi_tetvr.render.surfaces import split_shapes

if TYPE_CHECKING:
    from mi_tetvr.render.optical import OpticalModel
    from mi_tetvr.render.probes import Probe


def pack_links(tets: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Links ``4 * tet + face`` (int64), ``-1`` where ``tets < 0``.

    Parameters
    ----------
    tets : (k,) or (m, 4) int
        Tet indices (``-1`` for none).
    faces : same shape, int
        Local face indices in those tets.
    """
    tets = np.asarray(tets, np.int64)
    return np.where(tets >= 0, tets * 4 + np.asarray(faces, np.int64), -1)


def offset_links(links: np.ndarray, tet_offset: int) -> np.ndarray:
    """Links of a mesh whose tets start at ``tet_offset`` in a concatenation."""
    links = np.asarray(links, np.int64)
    return np.where(links >= 0, links + 4 * int(tet_offset), -1)


def owned(cls: type[dr.ArrayBase], array: np.ndarray) -> dr.ArrayBase:
    """``array`` (NumPy) as a Dr.Jit array of type ``cls`` in memory of Dr.Jit's
    own. Dr.Jit maps a NumPy array's memory without copying it: a later change
    of the NumPy array would show in the scene, and the array's alignment,
    which varies from one run to the next, changes the kernels generated from
    it (their loads' alignment), so that they miss Dr.Jit's kernel cache and
    compile again in every process."""
    x = cls(array)
    if dr.width(x) == 0:
        return x
    zero = dr.opaque(cls, 0)            # (an opaque zero: not folded away)
    x = (x | zero) if dr.is_integral_v(cls) else x + zero
    dr.eval(x)
    return x


def unpack_link(link: mi.Int32 | mi.UInt32) -> tuple[mi.UInt32, mi.UInt32]:
    """``(tet, face)`` as ``UInt32`` of a Dr.Jit link (meaningless where the
    link is ``-1``)."""
    return mi.UInt32(link >> 2), mi.UInt32(link & 3)


#: Bits per axis of the Morton code that orders tets (2^30 cells in all).
MORTON_BITS = 10
#: Neighbour links between tets more than this many records apart count as
#: far jumps in memory (:func:`far_links`).
FAR_RECORDS = 1024
#: The tets are put in Morton order when more than this fraction of the
#: neighbour links jumps far: a random order (99 %), not the generated grids
#: and refined meshes (8-17 %, Morton order: 7-9 %), whose own order renders
#: faster (the vertices, which keep the mesh's order, follow it).
FAR_FRACTION = 0.5


def morton_order(points: np.ndarray) -> np.ndarray:
    """The order of ``points`` along the Morton (Z-order) curve of their
    bounding box: nearby points end up nearby in memory."""
    points = np.asarray(points, np.float64)
    if not len(points):
        return np.zeros(0, np.int64)
    lo, hi = points.min(0), points.max(0)
    scale = (2 ** MORTON_BITS - 1) / np.where(hi > lo, hi - lo, 1.0)
    q = ((points - lo) * scale).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(MORTON_BITS):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def far_links(neighbors: np.ndarray) -> float:
    """Fraction of the interior neighbour links ``(m, 4)`` between tets more
    than :data:`FAR_RECORDS` records apart."""
    far = interior = 0
    for s in chunk_slices(len(neighbors)):
        nbr = neighbors[s].astype(np.int64)
        inside = nbr >= 0
        interior += np.count_nonzero(inside)
        far += np.count_nonzero(inside & (np.abs(nbr - np.arange(s.start, s.stop)[:, None])
                                          > FAR_RECORDS))
    return far / interior if interior else 0.0


def centroids(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m, 3) float64 centroids of the tets (in chunks: no (m, 4, 3) array)."""
    vertices = np.asarray(vertices, np.float64)
    out = np.empty((len(tets), 3))
    for s in chunk_slices(len(tets)):
        out[s] = vertices[tets[s]].mean(1)
    return out


def tets_of(cells: np.ndarray) -> np.ndarray:
    """(m, 4) view of the corners in the cells of :func:`shape_index_arrays`."""
    return np.asarray(cells).reshape(-1, 8)[:, :4]


def links_of(cells: np.ndarray) -> np.ndarray:
    """(m, 4) int32 view of the links in the cells of :func:`shape_index_arrays`."""
    return np.asarray(cells).reshape(-1, 8)[:, 4:].view(np.int32)


def shape_index_arrays(topology: Topology, vertices: np.ndarray,
                       reorder: bool | None = None) -> dict[str, np.ndarray]:
    """The index arrays a ``tetmesh`` shape hands the integrator (numpy,
    32-bit, indices local to the shape); see :class:`MeshBuffers` for their
    meaning: 32 bytes per tet (its cell: corners and links), 24 per boundary
    face.

    A mesh whose tets are listed in scattered order (more than
    :data:`FAR_FRACTION` of the neighbour links jump far in memory, see
    :func:`far_links`) has its tet records stored in the Morton order of
    the tets' centroids (``vertices`` are the positions): a ray's walk then
    reads nearby memory (1.55x faster on a shuffled 64^3 grid,
    ``benchmarks/bench_render.py --shuffle``). The order is the walk's alone:
    vertices, attributes and every other tet index stay as the mesh has
    them. ``reorder`` forces the choice. Reordered, the arrays also hold
    ``order``: the mesh's index of each stored tet (for cell data).
    """
    m = topology.n_tets
    if 4 * m >= 2 ** 31 or len(vertices) >= 2 ** 32:
        raise ValueError(f"a tet mesh of {m:,} tets and {len(vertices):,} vertices is too "
                         f"large for 32-bit links and indices")
    if reorder is None:
        reorder = far_links(topology.neighbors) > FAR_FRACTION
    tets, nbr, nface = topology.tets, topology.neighbors, topology.neighbor_faces
    btets = topology.boundary_tets
    order = None
    if reorder and m:
        order = morton_order(centroids(vertices, tets))
        rank = np.empty(m, np.int32)
        rank[order] = np.arange(m, dtype=np.int32)
        tets, nbr, nface, btets = tets[order], nbr[order], nface[order], rank[btets]
        nbr = np.where(nbr >= 0, rank[np.maximum(nbr, 0)], -1)
        del rank
    cells = np.empty((m, 8), np.uint32)
    cells[:, :4] = tets
    # (the links written into the cells a chunk at a time: no (m, 4) temporaries)
    links = cells[:, 4:].view(np.int32)
    for s in chunk_slices(m):
        np.multiply(nbr[s], 4, out=links[s], casting="unsafe")
        links[s] += nface[s]
        links[s][nbr[s] < 0] = -1
    del nbr, nface
    out = dict(
        cells=cells.ravel(),
        boundary=pack_links(btets, topology.boundary_local_faces).astype(np.uint32),
        faces=topology.boundary_faces.astype(np.uint32).ravel(),
        face_adj=topology.boundary_adjacency.astype(np.int32).ravel(),
    )
    if order is not None:
        out["order"] = order.astype(np.uint32)
    return out


#: The Dr.Jit and numpy types of the walk's index buffers (:class:`MeshBuffers`).
INDEX_TYPES = {"cells": (mi.UInt32, np.uint32), "boundary": (mi.UInt32, np.uint32),
               "faces": (mi.UInt32, np.uint32), "face_adj": (mi.Int32, np.int32)}


def drjit_index_arrays(arrays: dict[str, np.ndarray]) -> dict[str, mi.UInt32 | mi.Int32]:
    """:func:`shape_index_arrays`' arrays as the Dr.Jit buffers the walk reads
    (what a ``tetmesh`` shape keeps: the numpy arrays can go)."""
    return {k: owned(INDEX_TYPES[k][0], np.ascontiguousarray(arrays[k], INDEX_TYPES[k][1]))
            for k in INDEX_TYPES}


class MeshBuffers:
    """Flat Dr.Jit buffers of the geometry of a scene's tet meshes.

    cells : UInt32 (8 m)         per tet its four corners (global vertex indices) and the
                                 link to the face across each local face (Int32 bits, -1
                                 on the boundary): one 32-byte record (:meth:`corners`,
                                 :meth:`link`)
    boundary : UInt32 (b)        link of each boundary face (tet behind it, local face)
    faces : UInt32 (3 b)         boundary face vertices (outward)
    face_adj : Int32 (3 b)       boundary face across the edge opposite each corner
    positions : Float (3 n)      vertex positions (differentiable)
    record : Float (w n)         (a walk's, :meth:`with_record`) per vertex its position
                                 and the optical model's values, in one packet
    """
    DRJIT_STRUCT = {"cells": mi.UInt32, "boundary": mi.UInt32, "faces": mi.UInt32,
                    "face_adj": mi.Int32, "positions": mi.Float, "record": mi.Float}

    def __init__(self, cells: mi.UInt32 | None = None, boundary: mi.UInt32 | None = None,
                 faces: mi.UInt32 | None = None, face_adj: mi.Int32 | None = None,
                 positions: mi.Float | None = None, record: mi.Float | None = None) -> None:
        self.cells, self.boundary, self.faces = cells, boundary, faces
        self.face_adj, self.positions, self.record = face_adj, positions, record

    @property
    def n_tets(self) -> int:
        return dr.width(self.cells) // 8

    def corners(self, tet: mi.UInt32, active: bool | mi.Bool = True) -> mi.Array4u:
        """The four corners of ``tet`` (one 16-byte read)."""
        return dr.gather(mi.Array4u, self.cells, 2 * tet, active)

    def link(self, tet: mi.UInt32, f: mi.UInt32, active: bool | mi.Bool = True) -> mi.Int32:
        """The link across local face ``f`` of ``tet`` (in the same cache line as
        its corners)."""
        return dr.reinterpret_array(mi.Int32, dr.gather(mi.UInt32, self.cells, 8 * tet + 4 + f,
                                                        active))

    def position(self, i: mi.UInt32, active: bool | mi.Bool = True,
                 reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> mi.Point3f:
        """Position of vertex ``i``; ``reduce`` is the scatter strategy of the
        gather's reverse-mode derivative (gradients of shared vertices meet there)."""
        if self.record is not None:
            p = self.packet(i, active)
            return mi.Point3f(p[0], p[1], p[2])
        return dr.gather(mi.Point3f, self.positions, i, active, mode=reduce)

    def packet(self, i: mi.UInt32, active: bool | mi.Bool = True) -> Any:
        """Vertex ``i``'s packet of the :attr:`record` (one read of all its
        floats; the reads of one vertex's position and values are one)."""
        w = dr.width(self.record) // (dr.width(self.positions) // 3)
        return dr.gather(_packet_type(), self.record, i, active, shape=(w, dr.width(i)))

    def with_record(self, values: list[mi.Float]) -> MeshBuffers:
        """These buffers with a :attr:`record` of each vertex's position and
        ``values`` (each of one float per vertex), padded to a power of two
        floats: the walk reads a vertex it crosses in one packet (instead of
        a gather per float, from as many buffers). Built once per walk (an
        ``8 n`` floats kernel for colors and opacities; what a walk reads per
        step: ``bench_step.py``). Built from parameters that AD tracks, the
        record is tracked too, so that Dr.Jit's AD of a walk reaches them;
        the adjoint's passes build it from detached ones."""
        n = dr.width(self.positions) // 3
        idx = dr.arange(mi.UInt32, n)
        leaves = [dr.gather(mi.Float, self.positions, 3 * idx + j) for j in range(3)]
        leaves += list(values)
        w = 1 << (len(leaves) - 1).bit_length()
        leaves += [dr.zeros(mi.Float, n)] * (w - len(leaves))
        record = dr.zeros(mi.Float, w * n)
        # (one packet scatter: one kernel)
        dr.scatter(record, _packet_type()(*leaves), idx)
        dr.eval(record)
        return MeshBuffers(self.cells, self.boundary, self.faces, self.face_adj,
                           self.positions, record)


@functools.cache
def _packet_type_of(module: str) -> type:
    return importlib.import_module(module).ArrayXf


def _packet_type() -> type:
    """The variant's ``ArrayXf``: a packet of floats per lane (a gather or
    scatter of one reads or writes them together)."""
    return _packet_type_of(mi.Float.__module__)


def scene_tetmeshes(scene: mi.Scene) -> list[mi.Mesh]:
    """The scene's ``tetmesh`` shapes (its other shapes are surfaces:
    :mod:`mi_tetvr.render.surfaces`)."""
    return split_shapes(scene)[0]


def index_buffers(shapes: list[mi.Mesh]) -> tuple[dict[str, mi.UInt32 | mi.Int32], list[int]]:
    """The shapes' index buffers (:func:`drjit_index_arrays`) concatenated
    with their offsets applied: one shape's own buffers as they are (no copy).

    Returns
    -------
    (dict of MeshBuffers index fields, list of int)
        The buffers and each shape's first global boundary face.
    """
    if len(shapes) == 1:
        return dict(shapes[0].tet_buffers), [0]
    vo = to = fo = 0
    idx = {k: [] for k in INDEX_TYPES}
    face_offsets = []
    for s in shapes:
        b = {k: np.asarray(v) for k, v in s.tet_buffers.items()}
        cells = np.empty((len(b["cells"]) // 8, 8), np.uint32)
        cells[:, :4] = tets_of(b["cells"]).astype(np.int64) + vo
        cells[:, 4:] = offset_links(links_of(b["cells"]), to).astype(np.int32).view(np.uint32)
        idx["cells"].append(cells.ravel())
        idx["boundary"].append(offset_links(b["boundary"], to))
        idx["faces"].append(b["faces"].astype(np.int64) + vo)
        idx["face_adj"].append(np.where(b["face_adj"] >= 0,
                                        b["face_adj"].astype(np.int64) + fo, -1))
        face_offsets.append(fo)
        vo += s.vertex_count()
        to += len(cells)
        fo += s.face_count()
    if vo >= 2 ** 32 or 4 * to >= 2 ** 31:
        raise ValueError("tet meshes too large for 32-bit indices")
    return ({k: owned(t, np.concatenate(idx[k]).astype(nt)) for k, (t, nt) in INDEX_TYPES.items()},
            face_offsets)


def concat(buffers: list[mi.Float]) -> mi.Float:
    """One buffer of several shapes' buffers (no copy for a single shape)."""
    return buffers[0] if len(buffers) == 1 else dr.concat(buffers)


class TetGroup:
    """What a walk reads for one group of tet meshes (those of one optical
    model, or one mesh where meshes overlap; "scene" is left to Mitsuba's
    ``mi.Scene``): the shapes (to map Mitsuba's intersections to global
    boundary faces), their :class:`MeshBuffers`, the optical model and its
    parameter buffers.

    Parameters
    ----------
    shapes : list of tetmesh shapes
    face_offsets : list of int
        First global boundary face of each shape.
    buf : MeshBuffers
    model : mi_tetvr.render.optical.OpticalModel
    params : model.Params
    """

    def __init__(self, shapes: list[mi.Mesh], face_offsets: list[int], buf: MeshBuffers,
                 model: OpticalModel | Probe, params: Any) -> None:
        self.shapes, self.face_offsets = shapes, face_offsets
        self.buf, self.model, self.params = buf, model, params

    def detached(self) -> TetGroup:
        """The same group with its buffers detached from the AD graph."""
        return TetGroup(self.shapes, self.face_offsets, dr.detach(self.buf), self.model,
                        dr.detach(self.params))

    def walked(self) -> TetGroup:
        """The same group laid out for a walk: where the model's values of a
        vertex are the same for every ray (``model.per_ray_values`` False),
        its buffers carry a record of each vertex's position and values
        (:meth:`MeshBuffers.with_record`), which :meth:`values` reads."""
        if self.model.per_ray_values or self.buf.record is not None:
            return self
        n = dr.width(self.buf.positions) // 3
        values = scalar_leaves(self.model.gather(self.params, dr.arange(mi.UInt32, n)))
        return TetGroup(self.shapes, self.face_offsets, self.buf.with_record(values),
                        self.model, self.params)

    def values(self, i: mi.UInt32, active: bool | mi.Bool = True) -> Any:
        """The model's values (``Attributes``) of vertex ``i``: from the
        buffers' record where there is one (the same packet as its
        position), else the model's gather."""
        if self.buf.record is None:
            return self.model.gather(self.params, i, active)
        p = self.buf.packet(i, active)
        return from_scalar_leaves(dr.zeros(self.model.Attributes), [p[3 + j] for j in range(
            len(p) - 3)])

    def for_ray(self, d: mi.Vector3f) -> TetGroup:
        """The same group, its parameters for rays of direction ``d``
        (:meth:`~mi_tetvr.render.optical.OpticalModel.for_ray`)."""
        return TetGroup(self.shapes, self.face_offsets, self.buf, self.model,
                        self.model.for_ray(self.params, d))

    def owns(self, si: mi.PreliminaryIntersection3f) -> mi.Bool:
        """Whether a preliminary intersection is on one of :attr:`shapes`."""
        mask = mi.Bool(False)
        for shape in self.shapes:
            mask |= si.shape == mi.ShapePtr(shape)
        return mask

    def boundary_face(self, si: mi.PreliminaryIntersection3f) -> mi.UInt32:
        """Global boundary face index of a preliminary intersection."""
        idx = mi.UInt32(si.prim_index)
        if len(self.shapes) == 1:
            return idx
        off = mi.UInt32(0)
        for shape, offset in zip(self.shapes, self.face_offsets):
            off = dr.select(si.shape == mi.ShapePtr(shape), offset, off)
        return idx + off


def model_groups(shapes: list[mi.Mesh]) -> list[list[mi.Mesh]]:
    """The shapes in groups that one walk renders: the shapes of one optical
    model share a group (their buffers concatenated), except models with
    per-shape settings (``model.per_shape``: a transfer function's range and
    texels), whose shapes each form their own. Groups keep the scene's order."""
    groups, shared = [], {}
    for s in shapes:
        model = s.optical_model
        if model.per_shape:
            groups.append([s])
        elif model in shared:
            shared[model].append(s)
        else:
            shared[model] = [s]
            groups.append(shared[model])
    return groups


def tet_group(shapes: list[mi.Mesh], index: dict[str, mi.UInt32 | mi.Int32],
              face_offsets: list[int], **model_options: Any) -> TetGroup:
    """The :class:`TetGroup` of ``shapes`` (one group of
    :func:`model_groups`) from their concatenated index buffers
    (:func:`index_buffers`); positions and the optical model's parameters
    are read from the shapes (attached to their AD graph).
    ``model_options`` go to the optical model's constructor."""
    models = {s.optical_model for s in shapes}
    if len(models) > 1:
        raise ValueError(f"tetvr: the shapes of one walk must use one optical model, got "
                         f"{sorted(m.__name__ for m in models)} (see model_groups)")
    model = models.pop()(**model_options)
    buf = MeshBuffers(**index, positions=concat([s.vertex_positions_buffer() for s in shapes]))
    return TetGroup(shapes, face_offsets, buf, model, model.read_params(shapes))
