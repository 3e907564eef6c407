"""The ``tetmesh`` shape: a tetrahedral mesh with per-vertex color and opacity.

.. pluginparameters::

 * - filename
   - |string|
   - Mesh file in any volume format meshio reads (.vtu, .vtk, .msh, .mesh, ...);
     VTK reads the VTK formats meshio cannot.
 * - vertices, tets, color, opacity, scalar, cell_scalar
   - |tensor|
   - Alternatively the arrays themselves: (n, 3) positions, (m, 4) indices,
     (n, 3) linear RGB and (n,) extinction, or an (n,) scalar or an (m,)
     cell scalar (one value per tet) for a ``transfer_function`` (see
     :func:`mi_tetvr.tetmesh_dict`).
 * - color_attribute
   - |string|
   - Point-data array holding the color. (Default: ``color``)
 * - opacity_attribute
   - |string|
   - Point-data array holding the opacity. (Default: ``opacity``)
 * - scalar_attribute
   - |string|
   - Scalar array to classify with ``transfer_function``: point data, or
     (``post`` classification) cell data, rendered as it is, constant in
     each tet. (Default: the only scalar point array, else the only scalar
     cell array).
 * - transfer_function
   - |string|
   - DiffTetVR XML or project or ParaView JSON transfer function, or the name
     of one that ships with mi_tetvr (``default``, ``engine``, ...) or of a
     matplotlib colormap; when given, color and opacity come from the scalar
     field. (Default: none)
 * - value_min, value_max
   - |float|
   - Scalar range mapped to [0, 1] by the transfer function. (Default: the
     field's range)
 * - opacity_scale
   - |float|
   - Multiplies the transfer function's opacity. (Default: 1)
 * - classification
   - |string|
   - With a transfer function: ``post`` classifies the interpolated scalar
     along every ray (exact between the transfer function's texels; its
     scalar and texels are differentiable), ``preintegrated`` does the same
     by Weiler et al.'s pre-integrated table (faster, approximate, no
     derivatives), ``pre`` shades the vertices at load and interpolates the
     colors. (Default: ``post``)
 * - tf_color, tf_opacity
   - |tensor|
   - Instead of a ``transfer_function`` file (array input): the texels
     themselves, (R, 3) linear RGB and (R,) extinction at the centres
     ``(k + 0.5) / R`` of the normalised scalar axis. (Default: none)
 * - model
   - |string|
   - ``emission`` (emission and absorption) or ``absorption`` (X-ray
     attenuation: the opacity is the attenuation per unit length, nothing is
     emitted, ``alpha`` is one minus the transmittance). (Default: ``emission``)
 * - shade
   - |bool|
   - With ``post`` classification: light the volume by a headlight, as
     ParaView's *Shade* (:class:`~mi_tetvr.render.optical.Shaded`): the
     color times ``ambient + diffuse |n.d|`` plus ``specular |n.d|^specular_power``,
     ``n`` the scalar's gradient in each tet. (Default: false)
 * - ambient, diffuse, specular, specular_power
   - |float|
   - The lighting's coefficients. (Default: 0.1, 0.7, 0.2, 10, VTK's)
 * - tf_resolution
   - |int|
   - Texels the transfer function is resampled to over
     ``[value_min, value_max]`` for post-classification (linear between
     texel centres, constant outside). (Default: 256)
 * - cell_to_point
   - |bool|
   - Average per-cell arrays onto the vertices, so that a cell array can be
     the ``scalar_attribute`` or color. (Default: false)
 * - repair
   - |bool|
   - Drop folded, flat and duplicate tets (a warning says which and what it
     did to the boundary) instead of refusing the mesh. (Default: false)
 * - albedo
   - |float|, |color|, |tensor| or |string|
   - Makes the mesh a participating medium that scatters light
     (:class:`~mi_tetvr.render.optical.Scattering`, rendered by the
     ``tetpath`` integrator): its single-scattering albedo, constant, or
     (n,) / (n, 3) per vertex, linear RGB in [0, 1], or ``color``: the
     mesh's color is its albedo (its color array, or a transfer function's
     colors, classified at the vertices: ``classification`` ``pre``). The
     opacity is the extinction. (Default: none: emission and absorption only)
 * - albedo_attribute
   - |string|
   - Instead of ``albedo``: the point-data array (n,) or (n, 3) holding it.
     (Default: none)
 * - emission, emission_attribute
   - |float|, |color|, |tensor| or |string|
   - With an albedo: the medium's emission per unit extinction (as the
     color of an emission-absorption mesh), constant, per vertex or a
     point-data array. (Default: 0)
 * - phase
   - |phase|
   - With an albedo: the phase function, a Mitsuba phase plugin as a child
     (``isotropic``, ``hg``, ``rayleigh``, ...); its parameters are in
     ``mi.traverse`` under ``<id>.phase.``. (Default: ``isotropic``)
 * - sh
   - |tensor|
   - View-dependent colors: per vertex the coefficients of real spherical harmonics
     up to degree 0 to 3 (:class:`~mi_tetvr.render.optical.ViewDependent`), (n, K, 3)
     or (n, 3 K) with K = 1, 4, 9 or 16 RGB triples, degree by degree (3D Gaussian
     Splatting's order and offset: seen along ``d``, a vertex's color is
     ``max(sum_k Y_k(d) sh_k + 0.5, 0)``). A mesh file's point array ``sh`` is read
     the same way. Instead of ``color``; not with a transfer function or an albedo.
     (Default: none)
 * - to_world
   - |transform|
   - Applied to the vertex positions at load. Opacity stays per unit length
     of world space. (Default: identity)

Missing color defaults to white (1, 1, 1), missing opacity to 1 per unit length.
``scalar_attribute``, ``value_min``/``value_max`` and ``opacity_scale``
without a ``transfer_function``, or one of ``value_min``/``value_max``
without the other, are errors.

The shape keeps its topology only as the walk's 32-bit index buffers (32
bytes per tet); ``shape.oriented_tets()`` reads its tets back, positively
oriented (e.g. for the quality regularizer).

Differentiable parameters (``mi.traverse``): ``vertex_positions`` (3n),
``vertex_color`` (3n) and ``vertex_opacity`` (n); view-dependent (``sh``):
``vertex_sh`` (3Kn) instead of ``vertex_color``; scattering (an
``albedo``): ``vertex_emission`` (3n) and ``vertex_albedo`` (3n) instead of
``vertex_color``, and the phase function's (``phase.g``, ...); post-classified:
``vertex_positions``, ``vertex_scalar`` (n), ``tf_color`` (3R, linear RGB)
and ``tf_opacity`` (R, extinction per unit length); with cell data,
``cell_scalar`` (m, in the mesh's tet order) instead of ``vertex_scalar``.
After changing them,
``params.update()`` rebuilds the boundary's BVH; the topology stays.

.. code-block:: python

    'volume': {
        'type': 'tetmesh',
        'filename': 'scenes/meshes/blob.vtu',
    }

A mesh whose topology was built already (a ``TetMesh``, a fit's mesh) is
handed to the shape in Python: :func:`mi_tetvr.tetmesh_shape` builds the shape
object with it (the topology reaches the shape under a key, its ``topology``
property), which goes into the ``mi.load_dict`` scene as it is, under the id its
parameters are named by:

.. code-block:: python

    'volume': mi_tetvr.tetmesh_shape(mesh),          # a TetMesh: its topology
    'volume': mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(v, t), topology=topo),
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import numpy.typing as npt

from mi_tetvr.mesh.topology import Topology, convex_boundary, longest_edges
from mi_tetvr.plugins import constructor
from mi_tetvr.render.buffers import drjit_index_arrays, owned, shape_index_arrays, tets_of
from mi_tetvr.render.optical import (CellClassified, EmissionAbsorption, PostClassified,
                                     Scattering)
from mi_tetvr.render.properties import (LIGHTING, LIGHTING_DEFAULTS, MODELS,
                                        mesh_from_properties, post_classification, scattering,
                                        spherical_harmonics, transfer_function)


class TetMeshShape(mi.Mesh):
    __doc__ = __doc__
    #: The optical model that integrates this shape's vertex attributes.
    optical_model = EmissionAbsorption

    def __init__(self, props: mi.Properties) -> None:
        mesh = mesh_from_properties(props)
        post = post_classification(props, mesh)
        model = str(props.get("model", "emission")).lower()
        if model not in MODELS:
            raise ValueError(f"tetmesh: model must be one of {tuple(MODELS)}, got {model!r}")
        if model != "emission":
            if post is not None or transfer_function(props) is not None:
                raise ValueError(f"tetmesh: model '{model}' takes a per-vertex opacity, not a "
                                 f"transfer function")
        scatter = scattering(props, mesh)
        if scatter is not None and (model != "emission" or post is not None):
            raise ValueError("tetmesh: an albedo makes a scattering medium of a per-vertex "
                             "opacity (extinction): it takes no 'model', and a transfer "
                             "function only classified at the vertices (classification 'pre')")
        sh = spherical_harmonics(props, mesh)
        if sh is not None and (model != "emission" or post is not None or scatter is not None
                               or transfer_function(props) is not None):
            raise ValueError("tetmesh: spherical harmonics ('sh') are an emission-absorption "
                             "mesh's view-dependent colors: no transfer function, albedo or "
                             "'model' with them")
        topo = mesh.topology
        super().__init__("tetmesh", len(mesh.vertices), len(topo.boundary_faces),
                         props, False, False)
        if self.is_emitter():
            raise ValueError("tetmesh: a tet volume cannot be an area emitter; it emits through "
                             "its colors (color, or a transfer function): remove its 'area' "
                             "emitter")
        self.optical_model = MODELS[model]
        #: The phase function of a scattering mesh (else None).
        self.phase = None
        if scatter is not None:
            self.optical_model = Scattering
            albedo, emission, self.phase = scatter
            values = {"vertex_emission": emission, "vertex_opacity": mesh.opacity,
                      "vertex_albedo": albedo}
        elif sh is not None:
            self.optical_model = sh[0]
            values = {"vertex_sh": sh[1], "vertex_opacity": mesh.opacity}
        elif post is None:
            values = self.optical_model.vertex_values(mesh)
        else:
            self.optical_model, scalar, self.value_range, color, opacity = post
            #: The longest chord of any tet (the pre-integrated table's range).
            self.longest_edge = float(longest_edges(mesh.vertices, mesh.tets).max())
            self.tf_resolution = len(opacity)
            self.tf_color = owned(mi.Float, np.asarray(color, np.float32).ravel())
            self.tf_opacity = owned(mi.Float, np.asarray(opacity, np.float32))
            values = {"vertex_scalar": scalar}
            #: ``shade``'s coefficients (ambient, diffuse, specular, power).
            self.lighting = tuple(float(props.get(k, v)) for k, v in
                                  zip(LIGHTING, LIGHTING_DEFAULTS))
            if min(self.lighting) < 0.0:
                raise ValueError(f"tetmesh: the lighting's coefficients must be >= 0, got "
                                 f"{dict(zip(LIGHTING, self.lighting))}")
            if self.optical_model is CellClassified:
                #: The scalar per tet, in the mesh's order (cell data).
                self.cell_scalar = owned(mi.Float, np.asarray(scalar, np.float32))
        attributes = self.optical_model.vertex_attributes
        for name, channels in attributes:
            # Mitsuba's add_attribute takes a sequence of floats and converts them one by
            # one (6 s for the colors and opacities of 2M vertices as Dr.Jit arrays): it
            # gets a list of one shared zero, and the buffer itself is assigned below
            self.add_attribute(name, channels, [0.0] * (channels * len(mesh.vertices)))
        params = mi.traverse(self)
        params["vertex_positions"] = owned(mi.Float, mesh.vertices.astype(np.float32).ravel())
        params["faces"] = owned(mi.UInt32, topo.boundary_faces.astype(np.uint32).ravel())
        for name, channels in attributes:
            params[name] = owned(mi.Float, np.asarray(values[name], np.float32).ravel())
        params.update()
        arrays = shape_index_arrays(topo, mesh.vertices)
        #: Index buffers of the walk (Dr.Jit, local indices; see
        #: mi_tetvr.render.buffers): all the shape keeps of its topology
        self.tet_buffers = drjit_index_arrays(arrays)
        #: The mesh's index of each tet the walk stores, where it reorders
        #: them (cell data is read through it), else None.
        self.cell_order = owned(mi.UInt32, arrays["order"]) if (
            "order" in arrays and self.optical_model is CellClassified) else None
        self.tet_count = topo.n_tets
        self._convex = convex_boundary(mesh.vertices.astype(np.float32), topo.boundary_faces,
                                       topo.boundary_adjacency)

    def convex(self) -> bool:
        """Whether the mesh's boundary bounds a convex body
        (:func:`~mi_tetvr.mesh.topology.convex_boundary`, for the positions
        it has now): a ray that leaves it never comes back, so the walk asks
        the ray tracer once per ray (:func:`~mi_tetvr.render.cursor.traverse`).
        After the positions change it is found again from them (read back)."""
        if self._convex is None:
            # (the boundary's vertices alone read back)
            b = self.tet_buffers
            faces = np.asarray(b["faces"]).reshape(-1, 3)
            ids, local = np.unique(faces, return_inverse=True)
            P = dr.gather(mi.Point3f, self.vertex_positions_buffer(), mi.UInt32(ids))
            self._convex = convex_boundary(np.asarray(dr.detach(P), np.float32).T,
                                           local.reshape(-1, 3),
                                           np.asarray(b["face_adj"]).reshape(-1, 3))
        return self._convex

    def parameters_changed(self, keys: list[str] = []) -> None:  # noqa: B006 (Mitsuba's)
        super().parameters_changed(keys)
        if not keys or "vertex_positions" in keys:
            self._convex = None

    def set_mesh(self, params: mi.SceneParameters, vertices: npt.ArrayLike, tets: npt.ArrayLike,
                 values: dict[str, npt.ArrayLike], topology: Topology | None = None) -> None:
        """Give the shape another mesh in place: new vertices, tets and
        per-vertex values (``{attribute name: array}``, the names of
        ``optical_model.vertex_attributes``), written into ``params`` (the
        scene's ``mi.traverse``, whose ``update()`` then rebuilds the
        scene's BVH; the caller calls it). The shape object stays, and with
        it every object id that Mitsuba's kernels hold as constants: a
        refined mesh renders with the kernels compiled already (a new shape
        in a new scene compiles them again, seconds on a CPU)."""
        from mi_tetvr.mesh.topology import build_topology
        if self.optical_model is CellClassified or issubclass(self.optical_model,
                                                               PostClassified):
            raise ValueError("tetmesh: set_mesh replaces per-vertex colors, opacities or "
                             "albedos; a transfer function's mesh is built anew")
        vertices = np.asarray(vertices, np.float64)
        topo = build_topology(vertices, tets) if topology is None else topology
        prefix = f"{self.id()}."
        params[prefix + "vertex_positions"] = owned(mi.Float,
                                                    vertices.astype(np.float32).ravel())
        params[prefix + "faces"] = owned(mi.UInt32,
                                         topo.boundary_faces.astype(np.uint32).ravel())
        for name, channels in self.optical_model.vertex_attributes:
            a = np.asarray(values[name], np.float32).reshape(-1)
            if a.size != channels * len(vertices):
                raise ValueError(f"tetmesh: {name} needs {channels} value(s) per vertex for "
                                 f"{len(vertices)} vertices, got {a.size}")
            params[prefix + name] = owned(mi.Float, a)
        self.tet_buffers = drjit_index_arrays(shape_index_arrays(topo, vertices))
        self.tet_count = topo.n_tets

    def oriented_tets(self) -> np.ndarray:
        """(m, 4) int64: the shape's tets, positively oriented, in the walk's
        order (read from its index buffer), e.g. for
        :class:`~mi_tetvr.recon.regularizer.QualityRegularizer`."""
        return tets_of(np.asarray(self.tet_buffers["cells"])).astype(np.int64)

    def traverse(self, callback: mi.TraversalCallback) -> None:
        super().traverse(callback)
        if issubclass(self.optical_model, PostClassified):
            callback.put("tf_color", self.tf_color, mi.ParamFlags.Differentiable)
            callback.put("tf_opacity", self.tf_opacity, mi.ParamFlags.Differentiable)
        if self.optical_model is CellClassified:
            callback.put("cell_scalar", self.cell_scalar, mi.ParamFlags.Differentiable)
        if getattr(self, "phase", None) is not None:
            callback.put("phase", self.phase, mi.ParamFlags.Differentiable)

    def model_buffers(self) -> list[mi.Float]:
        """The differentiable buffers of the optical model besides the
        vertex attributes (the transfer function's texels, the cell scalar)."""
        out = ([self.tf_color, self.tf_opacity]
               if issubclass(self.optical_model, PostClassified) else [])
        return out + ([self.cell_scalar] if self.optical_model is CellClassified else [])

    def to_string(self) -> str:
        return (f"TetMeshShape[vertices={self.vertex_count()}, tets={self.tet_count}, "
                f"boundary_faces={self.face_count()}]")


mi.register_shape("tetmesh", constructor(TetMeshShape, "tetmesh"))
