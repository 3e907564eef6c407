"""The primal pass's per-ray results, kept for the derivative pass that
differentiates it.

``mi.render(scene, params)`` renders the image (``Integrator.render``) and,
when the loss is differentiated, calls ``render_backward`` (or
``render_forward``) with a *different* seed (``seed_grad``). Mitsuba's
derivative passes then trace the primal paths once more: a Monte Carlo
integrator needs the decorrelated samples for unbiased gradients. ``tetvr``
is deterministic given its rays, and its adjoint needs only each ray's final
value and transmittance (:mod:`mi_tetvr.render.adjoint`): so the derivative
pass reuses the rays of the primal render it differentiates (same sensor,
sample count and primal seed) and these per-ray results, instead of
rendering the image a second time. The gradient is then the exact derivative
of the image that ``mi.render`` returned.

A primal render is kept only while some differentiable input of the scene
(vertex positions, the optical model's vertex buffers, the environment's
parameters) has gradients enabled, and it is used only while those inputs
are the very same arrays (any update of a parameter makes a new array):
otherwise the derivative pass renders the primal itself, as Mitsuba does.
At most :data:`CAPACITY` renders are kept (the ``tetvr`` property
``kept_primals``; oldest dropped first): a derivative pass whose primal was
dropped renders it again, with a warning (the same gradients, one more
render's time).

The store is an explicit object, :class:`PrimalStates`, the integrator's
``kept_primals``. Its key is what the derivative pass is called with,
``(scene, sensor, seed, spp)``; an entry lives from the primal render that
puts it until the derivative pass that takes it (or until it is dropped).
The integrator's ``sample()`` keeps nothing: its ``render`` runs Mitsuba's
own pass on a ``Pass`` that hands the primal's per-ray state to the store,
and ``render_backward`` and ``render_forward`` run Mitsuba's on a ``Pass``
that returns the kept state as its primal
(:class:`mi_tetvr.plugins.tetvr.Pass`). (Mitsuba's scenes hold no Python
state and take no weak references, so a store per scene would keep scenes
alive or be fooled by a reused ``id``; this one holds the very input arrays
it was rendered with and compares them, so a reused ``id`` never matches.)
"""
from __future__ import annotations

import warnings
from collections import OrderedDict
from typing import Any

import drjit as dr
import mitsuba as mi

#: Primal renders kept at most (e.g. several views rendered before one
#: ``dr.backward``).
CAPACITY = 16


def derivative_seed(seed: int | mi.UInt32) -> int:
    """The seed ``mi.render`` gives the derivative pass of a primal render
    with ``seed`` when ``seed_grad`` is left at 0."""
    return int(mi.sample_tea_32(int(seed), 1)[0])


class PrimalStates:
    """Primal per-ray states keyed by what the derivative pass is called
    with: ``(scene, sensor, seed, spp)``."""

    def __init__(self, capacity: int = CAPACITY) -> None:
        self.capacity = int(capacity)
        if self.capacity < 1:
            raise ValueError(f"tetvr: kept_primals must be >= 1, got {capacity}")
        self._states = OrderedDict()
        self._dropped = OrderedDict()      # keys of the renders dropped (the latest 1024)

    @staticmethod
    def key(scene: mi.Scene, sensor: mi.Sensor, seed: int | mi.UInt32,
            spp: int) -> tuple[int, int, int, int]:
        return (id(scene), id(sensor), int(seed), int(spp))

    def put(self, key: tuple[int, int, int, int], primal_seed: int, state: Any,
            inputs: list[dr.ArrayBase]) -> None:
        """Keep ``state`` (per-ray arrays, scheduled for evaluation with the
        image) of a primal render with ``primal_seed``; ``inputs`` are the
        scene's differentiable arrays it was rendered with (references are
        held, so an in-place update copies them)."""
        dr.schedule(state)
        self._states.pop(key, None)
        self._states[key] = (int(primal_seed), state, list(inputs))
        self._dropped.pop(key, None)
        while len(self._states) > self.capacity:
            old, _ = self._states.popitem(last=False)
            self._dropped[old] = None
            if len(self._dropped) > 1024:
                self._dropped.popitem(last=False)

    def take(self, key: tuple[int, int, int, int],
             inputs: list[dr.ArrayBase]) -> tuple[int, Any] | None:
        """``(primal_seed, state)`` kept under ``key`` if it was rendered with
        exactly these ``inputs`` (removed either way), else None."""
        entry = self._states.pop(key, None)
        if entry is None:
            if self._dropped.pop(key, "absent") is None:
                warnings.warn(
                    f"tetvr: more than {self.capacity} primal renders awaited their "
                    f"derivative pass, and this one's was dropped: it renders its primal "
                    f"again (same gradients, one more render's time); raise the integrator's "
                    f"kept_primals to keep more", RuntimeWarning, stacklevel=3)
            return None
        seed, state, kept = entry
        same = len(kept) == len(inputs) and all(
            type(a) is type(b) and a.index == b.index for a, b in zip(kept, inputs))
        return (seed, state) if same else None

    def clear(self) -> None:
        self._states.clear()

    def __len__(self):
        return len(self._states)
