"""The Mitsuba plugins of mi_tetvr and their registration.

* :mod:`~mi_tetvr.plugins.tetmesh`: the ``tetmesh`` shape;
* :mod:`~mi_tetvr.plugins.tetvr`: the ``tetvr`` integrator (emission and
  absorption, probes, surfaces behind and inside the volume);
* :mod:`~mi_tetvr.plugins.tetproj`: the ``tetproj`` integrator (projections);
* :mod:`~mi_tetvr.plugins.tetpath`: the ``tetpath`` integrator (light transport).

The plugins are thin: each reads its properties and calls the renderer
(:mod:`mi_tetvr.render`). Nothing in the package imports them but
:func:`register`, which ``import mi_tetvr`` calls when a Mitsuba variant is set,
and which runs by itself whenever ``mi.set_variant`` switches to an autodiff RGB
variant (``llvm_ad_rgb``, ``cuda_ad_rgb``).

Each plugin module ends with its ``mi.register_*`` call, given the plugin's
:func:`constructor`: it keeps what the plugin raised, so that
:func:`mi_tetvr.load_dict` and its siblings raise the plugin's own exception
(:func:`raised_in`) where Mitsuba's parser passes on only its text.
"""
from __future__ import annotations

import collections
import copy
import graphlib
import importlib
import itertools
import sys
import threading
import types
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import mitsuba as mi

__all__ = ["register", "registered_variant", "on_variant_change", "variant_bound_modules",
           "rebind", "constructor", "mark", "raised_in", "PLUGINS"]

#: The plugin modules, registered in this order.
PLUGINS = ("tetmesh", "tetvr", "tetproj", "tetpath")

_registered = None


def registered_variant() -> str | None:
    """The Mitsuba variant the plugins are registered with (None: not yet)."""
    return _registered


def register() -> None:
    """Register the ``tetmesh`` shape and the ``tetvr``, ``tetproj`` and ``tetpath``
    integrators with the current Mitsuba variant.

    ``import mi_tetvr`` calls it when a variant is set, and it runs by itself
    after ``mi.set_variant`` switches to an autodiff RGB variant: the modules
    that bind the variant's types are reloaded for a new one (:func:`rebind`).
    Calling it again for the same variant does nothing.

    Raises
    ------
    RuntimeError
        Without a variant, or for one that is not an autodiff RGB variant.
    """
    global _registered
    import mitsuba as mi
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("mi_tetvr.register(): call mitsuba.set_variant(...) first "
                           "(e.g. 'llvm_ad_rgb' or 'cuda_ad_rgb')")
    if not variant.endswith("_rgb") or "_ad_" not in variant:
        raise RuntimeError(f"mi_tetvr needs an autodiff RGB variant (llvm_ad_rgb or "
                           f"cuda_ad_rgb), not '{variant}'")
    if variant == _registered:
        return
    if _registered is not None:
        rebind()                          # what the old variant bound, for the new one
    package = __name__.rpartition(".")[0]
    for name in PLUGINS:                  # each plugin module registers itself on import
        importlib.import_module(f"{package}.plugins.{name}")
    _registered = variant


def variant_bound_modules(package: str = "mi_tetvr") -> list[types.ModuleType]:
    """The imported modules of ``package`` that hold a Mitsuba variant's types or
    functions, in an order where each comes after the modules it takes names from.

    A module is bound when its globals hold Mitsuba or Dr.Jit (the modules, their types,
    functions or values) or names of another bound module (``from .walk import trace``
    binds the ``trace`` of the variant ``walk`` was imported for). Read from the modules
    themselves, so that no list of them can miss a new one.
    """
    modules = {n: m for n, m in list(sys.modules.items())
               if isinstance(m, types.ModuleType) and n != __name__   # (its state stays)
               and (n == package or n.startswith(package + "."))}

    variant, takes = set(), {}
    for name, module in modules.items():
        takes[name] = set()
        for value in list(vars(module).values()):
            # a module held (``import mitsuba as mi``, ``from . import walk``) is read at
            # call time, reloaded or not; only Mitsuba and Dr.Jit themselves bind a variant
            module_held = isinstance(value, types.ModuleType)
            where = value.__name__ if module_held else getattr(value, "__module__", None)
            if not isinstance(where, str) or where == name:
                continue
            if where.split(".")[0] in ("mitsuba", "drjit"):
                variant.add(name)
            elif where in modules and not module_held:
                takes[name].add(where)
    bound, grew = set(variant), True
    while grew:                           # and what takes names from a bound module
        grew = False
        for name, sources in takes.items():
            if name not in bound and sources & bound:
                bound.add(name)
                grew = True
    order = list(modules)                 # import order breaks ties (and any cycle)
    graph = {n: sorted(takes[n] & bound, key=order.index) for n in sorted(bound, key=order.index)}
    try:
        ranked = list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError:
        ranked = sorted(bound, key=order.index)
    return [modules[n] for n in ranked]


def rebind(package: str = "mi_tetvr") -> None:
    """Reload the modules bound to the variant (:func:`variant_bound_modules`), each
    after those it takes names from: the plugin modules among them register
    themselves again with the variant set now."""
    for module in variant_bound_modules(package):
        importlib.reload(module)


def on_variant_change(old: str | None, new: str | None) -> None:
    """Mitsuba's variant callback (``mi.detail.add_variant_callback``): register the
    plugins with each autodiff RGB variant Mitsuba switches to."""
    if new is not None and new.endswith("_rgb") and "_ad_" in new:
        register()


# -- a plugin's own exception ------------------------------------------------------------
#: What plugins' constructors raised lately: ``(number, exception, plugin, id)``.
_raised = collections.deque(maxlen=32)
_numbers = itertools.count(1)
_lock = threading.Lock()


def constructor(cls: type[mi.Object], name: str) -> Callable[[mi.Properties], mi.Object]:
    """The function Mitsuba calls to build the plugin ``name`` (class ``cls``) from
    its properties: it keeps a copy of what the constructor raises (see
    :func:`raised_in`) and lets it through."""
    def build(props):
        try:
            return cls(props)
        except Exception as e:
            _keep(e, name, props.id())
            raise
    build.__name__ = build.__qualname__ = f"build_{name}"
    return build


def _keep(exc, plugin, where):
    try:
        kept = copy.copy(exc)            # (the plugin's frames stay with the original)
    except Exception:
        kept = RuntimeError(f"{type(exc).__name__}: {exc}")
    kept.__traceback__ = kept.__context__ = kept.__cause__ = None
    kept.__suppress_context__ = False
    with _lock:
        _raised.append((next(_numbers), kept, plugin, where))


def mark() -> int:
    """The number of the last exception kept: :func:`raised_in` after it."""
    with _lock:
        return _raised[-1][0] if _raised else 0


def raised_in(error: BaseException, since: int = 0) -> tuple[BaseException, str, str] | None:
    """The exception a plugin's constructor raised that Mitsuba passed on in
    ``error`` (the ``RuntimeError`` of its parser), or None.

    Of the exceptions kept after ``since`` (:func:`mark`), those whose message
    ``error``'s text holds; of those, the innermost (a plugin that builds
    another passes the other's error on in its own) and the first raised. Where
    none is held in the text, the only one kept after ``since``, if just one
    was. The one returned is forgotten.

    Returns
    -------
    (BaseException, str, str) or None
        The exception (a copy of the one raised, without its traceback), the
        plugin that raised it and the id of the object it was building.
    """
    text = str(error)
    with _lock:
        recent = [r for r in _raised if r[0] > since]
        held = [r for r in recent if str(r[1]) and str(r[1]) in text]
        inner = [r for r in held if not any(o is not r and str(o[1]) in str(r[1])
                                            and str(o[1]) != str(r[1]) for o in held)]
        found = inner[0] if inner else (recent[0] if len(recent) == 1 and since else None)
        if found is not None:
            _raised.remove(found)
    return None if found is None else found[1:]
