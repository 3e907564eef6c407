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
At most :data:`CAPACITY` renders are kept (oldest dropped first).
"""
from __future__ import annotations

from collections import OrderedDict

import drjit as dr
import mitsuba as mi

#: Primal renders kept at most (e.g. several views rendered before one
#: ``dr.backward``).
CAPACITY = 16


def derivative_seed(seed):
    """The seed ``mi.render`` gives the derivative pass of a primal render
    with ``seed`` when ``seed_grad`` is left at 0."""
    return int(mi.sample_tea_32(int(seed), 1)[0])


class PrimalStates:
    """Primal per-ray states keyed by what the derivative pass is called
    with: ``(scene, sensor, seed, spp)``."""

    def __init__(self, capacity=CAPACITY):
        self.capacity = int(capacity)
        self._states = OrderedDict()

    @staticmethod
    def key(scene, sensor, seed, spp):
        return (id(scene), id(sensor), int(seed), int(spp))

    def put(self, key, primal_seed, state, inputs):
        """Keep ``state`` (per-ray arrays, scheduled for evaluation with the
        image) of a primal render with ``primal_seed``; ``inputs`` are the
        scene's differentiable arrays it was rendered with (references are
        held, so an in-place update copies them)."""
        dr.schedule(state)
        self._states.pop(key, None)
        self._states[key] = (int(primal_seed), state, list(inputs))
        while len(self._states) > self.capacity:
            self._states.popitem(last=False)

    def take(self, key, inputs):
        """``(primal_seed, state)`` kept under ``key`` if it was rendered with
        exactly these ``inputs`` (removed either way), else None."""
        entry = self._states.pop(key, None)
        if entry is None:
            return None
        seed, state, kept = entry
        same = len(kept) == len(inputs) and all(
            type(a) is type(b) and a.index == b.index for a, b in zip(kept, inputs))
        return (seed, state) if same else None

    def clear(self):
        self._states.clear()

    def __len__(self):
        return len(self._states)
