"""mi_tetvr: differentiable volume rendering of tetrahedral meshes in Mitsuba 3.

Usage::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")   # or "cuda_ad_rgb"
    import mi_tetvr                 # registers the `tetmesh` shape and `tetvr` integrator

Sub-packages (see the README's *Architecture*):

* :mod:`mi_tetvr.mesh` -- tet meshes in numpy: topology, files, generators,
  refinement, initial meshes (no Mitsuba variant needed);
* :mod:`mi_tetvr.render` -- the Dr.Jit renderer: the tet walk, optical models,
  the adjoint (needs a variant);
* :mod:`mi_tetvr.grid` -- regular-grid volumes and the grid ray marcher;
* :mod:`mi_tetvr.recon` -- cameras, data sets, the training loop behind
  ``mi-tetvr fit``, metrics;
* :mod:`mi_tetvr.transfer` -- transfer functions and their files;
  :mod:`mi_tetvr.color` -- the sRGB curve.

In a scene dict, :func:`tetmesh_dict` is a ``tetmesh`` entry made from arrays;
:func:`tetmesh_shape` is the shape itself, built from a ``TetMesh`` (or from an
entry and the topology of its arrays, built once and handed on).

A plugin that refuses its input raises ``ValueError`` (or :class:`MeshError`);
Mitsuba's parser passes it on as a ``RuntimeError`` holding the plugin's
traceback as text. :func:`load_dict`, :func:`load_file` and :func:`load_string`
are Mitsuba's, raising the plugin's own exception instead
(:func:`plugin_error` reads it back from such a ``RuntimeError``).

If no variant is set at import, call :func:`register` after
:func:`mitsuba.set_variant`.
"""
from __future__ import annotations

import builtins
import contextlib
import importlib
import re
import sys

from .mesh import MeshError, TetMesh, Topology, build_topology, quality, read_tetmesh, write_tetmesh
from .transfer import TransferFunction, read_transfer_function

__all__ = ["register", "tetmesh_dict", "tetmesh_shape", "load_dict", "load_file", "load_string",
           "plugin_error", "read_tetmesh", "write_tetmesh", "MeshError", "TetMesh", "Topology", "build_topology", "quality", "TransferFunction",
           "read_transfer_function"]

_registered_variant = None

#: Modules that bind Mitsuba/Dr.Jit types at import, in dependency order.
_VARIANT_MODULES = ("render.segment", "render.buffers", "render.geometry", "render.optical",
                    "render.adjoint", "render.walk", "render.transport", "render", "grid.marcher",
                    "recon.regularizer", "plugins.tetmesh", "plugins.tetvr", "plugins.tetproj",
                    "plugins.tetpath")


def register():
    """Register the ``tetmesh`` shape and ``tetvr`` integrator with the current
    Mitsuba variant (again after switching variants)."""
    global _registered_variant
    import mitsuba as mi
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("mi_tetvr.register(): call mitsuba.set_variant(...) first "
                           "(e.g. 'llvm_ad_rgb' or 'cuda_ad_rgb')")
    if not variant.endswith("_rgb") or "_ad_" not in variant:
        raise RuntimeError(f"mi_tetvr needs an autodiff RGB variant (llvm_ad_rgb or "
                           f"cuda_ad_rgb), not '{variant}'")
    if variant == _registered_variant:
        return
    from . import plugins  # noqa: F401
    # Modules that bind Mitsuba/Dr.Jit types at import are reloaded for a new variant.
    for name in _VARIANT_MODULES:
        full = f"{__name__}.{name}"
        if name.startswith("plugins.") or full in sys.modules:
            mod = importlib.import_module(full)
            if _registered_variant is not None:
                importlib.reload(mod)
    _registered_variant = variant


def tetmesh_dict(vertices, tets, color=None, opacity=None, scalar=None, cell_scalar=None,
                 **props):
    """A ``mi.load_dict`` entry for a ``tetmesh`` built from arrays.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    color : (n, 3) float, optional
    opacity : (n,) float, optional
    scalar : (n,) float, optional
        A scalar field for a ``transfer_function`` property.
    cell_scalar : (m,) float, optional
        Or a scalar per tet (cell data, constant in each tet).
    **props
        Other plugin properties (e.g. ``to_world``, ``transfer_function``,
        ``albedo``); numpy arrays become tensors.

    Raises
    ------
    ValueError
        Where the shape would refuse the scalar (two of them, none to map it,
        a constant one without ``value_min`` and ``value_max``), with the
        shape's message: here, before Mitsuba's parser would wrap it.
    """
    import mitsuba as mi
    import numpy as np
    d = {"type": "tetmesh",
         "vertices": mi.TensorXf(np.asarray(vertices, dtype=np.float32)),
         "tets": mi.TensorXi(np.asarray(tets, dtype=np.int32))}
    if color is not None:
        d["color"] = mi.TensorXf(np.asarray(color, dtype=np.float32))
    if opacity is not None:
        d["opacity"] = mi.TensorXf(np.asarray(opacity, dtype=np.float32))
    if scalar is not None:
        d["scalar"] = mi.TensorXf(np.asarray(scalar, dtype=np.float32))
    if cell_scalar is not None:
        d["cell_scalar"] = mi.TensorXf(np.asarray(cell_scalar, dtype=np.float32))
    # (other per-vertex arrays, e.g. a scattering mesh's albedo and emission)
    d.update({k: mi.TensorXf(np.asarray(v, dtype=np.float32)) if isinstance(v, np.ndarray) else v
              for k, v in props.items()})
    if scalar is not None or cell_scalar is not None:
        register()
        from .plugins.tetmesh import check_array_scalars
        check_array_scalars(d)
    return d


def tetmesh_shape(source, topology=None, **props):
    """The ``tetmesh`` shape itself, built now, for a scene dict: ``mi.load_dict``
    takes the object as it is, and the key it is under becomes its id (the prefix of
    its ``mi.traverse`` names, ``volume.vertex_color`` under ``"volume"``).

    Parameters
    ----------
    source : TetMesh or dict
        A mesh (its vertices, tets, color and opacity, and its topology, built by
        the mesh once and kept with it), or a ``tetmesh`` dict entry with the
        tensors ``vertices`` and ``tets`` (:func:`tetmesh_dict`'s).
    topology : Topology, optional
        :func:`build_topology` of those vertices and tets (any order of each
        tet's corners), when the caller has it: the shape does not build it
        again. Default: a ``TetMesh``'s own; for a dict, built by the shape.
    **props
        Other properties of the shape (``transfer_function``, ``scalar``, ...).

    Raises
    ------
    ValueError
        As the plugin does (:class:`MeshError` for a mesh it refuses), with
        its own message: a shape built here is not wrapped by Mitsuba's parser.
    """
    register()
    from .plugins.tetmesh import build_shape
    if isinstance(source, TetMesh):
        entry = tetmesh_dict(source.vertices, source.tets, source.color, source.opacity,
                             **props)
        topology = source.topology if topology is None else topology
    else:
        entry = {**source, **props}
    return build_shape(entry, topology)


#: Exception classes of the project a plugin may raise, besides Python's own.
_PLUGIN_EXCEPTIONS = {"MeshError": MeshError}


def plugin_error(exc):
    """The exception a plugin raised while Mitsuba built a scene, read back from
    the ``RuntimeError`` Mitsuba's parser raises for it.

    The parser's message is its own line (``[parser.cpp:...] At dictionary node
    "volume": failed to instantiate ...``) followed by the plugin's traceback as
    text; the traceback's last exception is the plugin's. It is returned as that
    exception again, its message alone: of the same class where it is one of
    Python's or :class:`MeshError`, else a ``RuntimeError`` saying
    ``"module.Name: message"``. Where Python allows (3.11), a note says which
    plugin raised it and where in the scene (``err.__notes__``).

    Parameters
    ----------
    exc : BaseException
        What ``mi.load_dict``, ``mi.load_file`` or ``mi.load_string`` raised.

    Returns
    -------
    BaseException
        The plugin's exception, or ``exc`` itself when it does not come from a
        plugin's constructor (Mitsuba's own errors, an unknown plugin type, ...).
    """
    text = str(exc)
    marker = "Traceback (most recent call last):"
    if not isinstance(exc, RuntimeError) or marker not in text:
        return exc
    head, _, trace = text.rpartition(marker)
    lines = [line for line in trace.splitlines() if line.strip()]
    # the frames are indented; the exception starts at the first line that is not
    first = next((i for i, line in enumerate(lines) if not line[0].isspace()), None)
    if first is None:
        return exc
    name, sep, message = lines[first].partition(": ")
    if not re.fullmatch(r"[\w.]+", name):        # not "Name: message" nor "Name"
        name, message = "", lines[first]
    message = "\n".join([message] + lines[first + 1:])
    module, _, short = name.rpartition(".")
    cls = getattr(builtins, short, None) if module in ("", "builtins") else None
    if cls is None and (module == "" or module.split(".")[0] == __name__):
        cls = _PLUGIN_EXCEPTIONS.get(short)
    if isinstance(cls, type) and issubclass(cls, Exception):
        err = cls(message)
    else:
        err = RuntimeError(f"{name}: {message}" if name else message)
    # the innermost plugin (one plugin's constructor may load another's scene)
    where = re.findall(r'At (.*?): failed to instantiate .*?plugin of type "([^"]+)"', head)
    if where and hasattr(err, "add_note"):
        err.add_note(f'(raised by the "{where[-1][1]}" plugin while Mitsuba loaded '
                     f'{where[-1][0]})')
    return err


@contextlib.contextmanager
def _plugin_errors():
    """Raise a plugin's own exception (:func:`plugin_error`) where Mitsuba's
    parser wraps it in a ``RuntimeError``; others pass unchanged."""
    try:
        yield
    except RuntimeError as e:
        err = plugin_error(e)
        if err is e:
            raise
        raise err from None      # (Mitsuba's whole text stays as its __context__)


def load_dict(scene, **kwargs):
    """``mi.load_dict``, a plugin's refusal raised as the plugin raised it
    (:func:`plugin_error`)."""
    import mitsuba as mi
    with _plugin_errors():
        return mi.load_dict(scene, **kwargs)


def load_file(path, **kwargs):
    """``mi.load_file`` (an XML scene), a plugin's refusal raised as the plugin
    raised it (:func:`plugin_error`)."""
    import mitsuba as mi
    with _plugin_errors():
        return mi.load_file(str(path), **kwargs)


def load_string(xml, **kwargs):
    """``mi.load_string`` (an XML scene in a string), a plugin's refusal raised
    as the plugin raised it (:func:`plugin_error`)."""
    import mitsuba as mi
    with _plugin_errors():
        return mi.load_string(xml, **kwargs)


def _auto_register():
    try:
        import mitsuba as mi
    except ImportError:
        return
    if mi.variant() is not None:
        register()


_auto_register()
