"""Tetrahedral meshes in numpy: primitives and topology, files, generators,
refinement and initial meshes.

Everything here is numpy (and meshio for files); it imports and runs without
a Mitsuba variant. Topology -- consistently oriented tets, the neighbour
across each face, the boundary faces and the tet behind each -- is built here
and only here, by :func:`build_topology`; the renderer takes it from there.

Algorithms are free functions over arrays (``vertices : (n, 3) float``,
``tets : (m, 4) int``); :class:`TetMesh` holds a mesh with its per-vertex
color and opacity and exposes them as cached properties.

Modules
-------
:mod:`~mi_tetvr.mesh.topology`
    Per-tet primitives (:data:`FACES`, :data:`EDGES`, :func:`signed_volumes`,
    :func:`orient_tets`, :func:`face_keys`, :func:`edge_lengths`,
    :func:`quality`), validation and :func:`build_topology`.
:mod:`~mi_tetvr.mesh.tetmesh`
    :class:`TetMesh`.
:mod:`~mi_tetvr.mesh.io`
    :func:`read_tetmesh`, :func:`write_tetmesh` (meshio formats).
:mod:`~mi_tetvr.mesh.generate`
    Regular tet grids and analytic fields on them.
:mod:`~mi_tetvr.mesh.refine`
    Edge-bisection refinement and pruning of empty tets.
:mod:`~mi_tetvr.mesh.initial`
    Initial meshes for reconstruction (grid, fTetWild, Delaunay).
:mod:`~mi_tetvr.mesh.scenes`
    The bundled scenes, their meshes and volume.
"""
from .topology import (EDGES, FACES, FLAT_TOLERANCE, MeshError, Orientation, Topology,
                       bbox_diagonal, build_topology, check_bounds, edge_lengths, face_keys,
                       flip_tets, format_summary, geometry_summary, mean_edge_length, orient_tets,
                       quality, repair_tets, signed_volumes, validate_arrays, validate_attributes)
from .tetmesh import DEFAULT_COLOR, DEFAULT_OPACITY, TetMesh
from .io import read_tetmesh, write_tetmesh
from .generate import KUHN_TETS, blob_field, blob_mesh, grid_mesh, grid_tets
from .refine import (PruneResult, RefineResult, bisection_order, prune_empty, prune_mesh,
                     refine_mesh, select_by_attribute, select_top_fraction, split_vertices)
from .initial import delaunay_init, grid_init, orient_and_compact, tetwild_init
from .scenes import bundled, default_volume, make_scenes

__all__ = [
    # topology: primitives, validation, topology
    "FACES", "EDGES", "FLAT_TOLERANCE", "MeshError", "Topology", "Orientation",
    "check_bounds", "signed_volumes", "bbox_diagonal", "flip_tets", "orient_tets", "face_keys",
    "edge_lengths", "mean_edge_length", "quality", "validate_arrays", "validate_attributes",
    "build_topology", "geometry_summary", "format_summary", "repair_tets",
    # the mesh class
    "TetMesh", "DEFAULT_COLOR", "DEFAULT_OPACITY",
    # files
    "read_tetmesh", "write_tetmesh",
    # generated meshes
    "KUHN_TETS", "grid_tets", "grid_mesh", "blob_field", "blob_mesh",
    # refinement
    "RefineResult", "PruneResult", "split_vertices", "bisection_order", "select_top_fraction",
    "select_by_attribute", "prune_empty", "refine_mesh", "prune_mesh",
    # initial meshes
    "grid_init", "tetwild_init", "delaunay_init", "orient_and_compact",
    # bundled scenes
    "make_scenes", "bundled", "default_volume",
]
