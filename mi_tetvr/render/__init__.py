"""The renderer in Dr.Jit: the tet walk, its media and probes, its adjoint,
and the ray program that composes them.

Modules, from the bottom up:

* :mod:`~mi_tetvr.render.pytree`: field-wise arithmetic on the walk's small
  structures;
* :mod:`~mi_tetvr.render.segment`: segment integrals (emission-absorption
  with sub-intervals, several media at once) and clipping a segment;
* :mod:`~mi_tetvr.render.surfaces`: the scene's other shapes, rendered by a
  nested integrator and seen through the volume;
* :mod:`~mi_tetvr.render.buffers`: the flat buffers the walk reads and the
  one encoding of neighbour links (``4 * tet + face``);
* :mod:`~mi_tetvr.render.geometry`: the ray frame, the consistent edge
  predicate, face crossings, one step through a tet, entry through the
  boundary;
* :mod:`~mi_tetvr.render.clipping`: a plane and a box that cut the volume;
* :mod:`~mi_tetvr.render.linear`: linear functions inside one tet;
* :mod:`~mi_tetvr.render.optical`: the media (what a crossing interpolates,
  how a piece is integrated);
* :mod:`~mi_tetvr.render.probes`: the probes (projections, slices,
  isosurfaces: what picks one value along a ray);
* :mod:`~mi_tetvr.render.cursor`: the one traversal (boundary entry, the
  walk, re-entry, a start point inside a mesh), each piece handed to a
  client;
* :mod:`~mi_tetvr.render.adjoint`: the derivative passes' context and the
  piece adjoint (the inversion trick, written once);
* :mod:`~mi_tetvr.render.walk`: ``tetvr``'s clients of the cursor
  (emission-absorption and probes, and their derivatives);
* :mod:`~mi_tetvr.render.merged`: meshes that overlap in space, one cursor
  each, walked together as one medium;
* :mod:`~mi_tetvr.render.layers`: surfaces inside the volume, composited
  front to back;
* :mod:`~mi_tetvr.render.replay`: the primal renders kept for their
  derivative passes;
* :mod:`~mi_tetvr.render.program`: the ray program (surfaces, clip,
  probes, media, what lies behind), built per scene.

The ``tetmesh`` shape and the ``tetvr`` and ``tetproj`` integrators
(``mi_tetvr.plugins``) are thin wrappers over these. Importing this package
needs a Mitsuba variant (``mi.set_variant('llvm_ad_rgb')`` or
``'cuda_ad_rgb'``).
"""
import mitsuba as _mi

if _mi.variant() is None:
    raise ImportError("mi_tetvr.render needs a Mitsuba variant: call "
                      "mitsuba.set_variant('llvm_ad_rgb') (or 'cuda_ad_rgb') first")

# What clients of the renderer build on: the media and probes to subclass (see the
# architecture page) and the ray program the integrators call. Everything else is
# imported from its module.
from mi_tetvr.render.optical import Absorption, EmissionAbsorption, OpticalModel  # noqa: E402
from mi_tetvr.render.probes import Isosurface, Probe, Projection, Slice  # noqa: E402
from mi_tetvr.render.program import VolumeProgram  # noqa: E402

__all__ = ["OpticalModel", "EmissionAbsorption", "Absorption", "Probe", "Projection", "Slice",
           "Isosurface", "VolumeProgram"]
