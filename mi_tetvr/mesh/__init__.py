"""Tet meshes in numpy: topology (the only place it is made), files,
generators, refinement and initial meshes."""
from .topology import (FACES, FLAT_TOLERANCE, MeshError, TetMesh, Topology, build_topology,
                       format_summary, geometry_summary, quality, signed_volumes,
                       validate_arrays, validate_attributes)
from .io import read_tetmesh, write_tetmesh
