"""The optimizer of a reconstruction: Adam over per-vertex scene parameters.

:class:`VertexAdam` wraps ``mi.ad.Adam`` and is the one place that knows the
layout of Adam's state. It keeps one base learning rate per parameter, hands
out Adam's moments per vertex (to carry them over when the mesh is refined)
and saves and loads them as numpy arrays (for checkpoints).
"""
from __future__ import annotations

from collections.abc import Mapping

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["VertexAdam"]


class VertexAdam(Mapping):
    """Adam over per-vertex parameters, each with its own learning rate.

    A read-only mapping from parameter key to its current value (so
    ``scene_params.update(opt)`` writes the values into a scene); values of
    registered keys can be overwritten with ``opt[key] = value`` (e.g. to
    clip them), which keeps Adam's moments.

    Parameters
    ----------
    params : mapping of key to Dr.Jit array (e.g. ``mi.SceneParameters``)
        Where the starting values come from.
    rates : dict of key to float
        The parameters to optimize (in this order) and their base learning
        rates.
    n_vertices : int
        Vertex count; each parameter holds ``n_vertices * c`` values (``c``
        per vertex).
    shared : sequence of keys
        Parameters that are not per vertex (a learned background): optimized
        and checkpointed, but not in :meth:`moments`.
    """

    def __init__(self, params, rates, n_vertices, shared=()):
        self.rates = dict(rates)
        self.n_vertices = int(n_vertices)
        self.shared = tuple(shared)
        self._adam = mi.ad.Adam(lr=next(iter(self.rates.values())))
        for k in self.rates:
            self._adam[k] = params[k]

    # -- values -----------------------------------------------------------------
    def __getitem__(self, key):
        return self._adam[key]

    def __setitem__(self, key, value):
        if key not in self.rates:
            raise KeyError(f"{key!r} is not optimized (keys: {list(self.rates)})")
        self._adam[key] = value

    def __contains__(self, key):
        return key in self.rates

    def __iter__(self):
        return iter(self.rates)

    def __len__(self):
        return len(self.rates)

    def clear_grads(self):
        """Zero the gradients of all parameters."""
        for k in self.rates:
            dr.clear_grad(self._adam[k])

    def step(self, lr_scale=1.0):
        """One Adam step over the accumulated gradients, each parameter with
        its base learning rate times ``lr_scale``."""
        for k, lr in self.rates.items():
            self._adam.set_learning_rate({k: lr * lr_scale})
        self._adam.step()

    # -- moments ----------------------------------------------------------------
    # Adam's state per key is (value, promoted, lr, (t, m, v, v_max)): the step
    # count t and the first and second moments m, v as flat arrays.
    def moments(self):
        """Adam's step count and moments per vertex.

        Returns
        -------
        dict of key to ``(t, m, v)``: ``t`` int, ``m`` and ``v`` (n_vertices, c) float32.
        """
        out = {}
        for k in self.rates:
            if k in self.shared:
                continue
            t, m, v = self._adam.state[k][3][:3]
            out[k] = (int(np.asarray(t).ravel()[0]), np.array(m).reshape(self.n_vertices, -1),
                      np.array(v).reshape(self.n_vertices, -1))
        return out

    def set_moments(self, moments):
        """Replace Adam's step count and moments (e.g. interpolated onto a
        refined mesh).

        Parameters
        ----------
        moments : dict of key to ``(t, m, v)``
            As :meth:`moments` gives them: ``m`` and ``v`` with
            ``n_vertices * c`` values each (any shape); keys that are not
            optimized are ignored.
        """
        for k, (t, m, v) in moments.items():
            if k not in self.rates:
                continue
            value, promoted, lr, extra = self._adam.state[k]
            m, v = (np.asarray(a, np.float32).ravel() for a in (m, v))
            if m.size != dr.width(value) or v.size != dr.width(value):
                raise ValueError(f"{k}: moments of {m.size} and {v.size} values for a "
                                 f"parameter of {dr.width(value)}")
            self._adam.state[k] = (value, promoted, lr,
                                   (type(extra[0])(int(t)), mi.Float(m), mi.Float(v), *extra[3:]))

    # -- save / load ------------------------------------------------------------
    def state_dict(self):
        """Adam's state as numpy arrays: ``{"<key>:t": (1,), "<key>:m": (n * c,),
        "<key>:v": (n * c,)}`` per key."""
        out = {}
        for k in self.rates:
            t, m, v = self._adam.state[k][3][:3]
            out[f"{k}:t"] = np.asarray(t)
            out[f"{k}:m"] = np.array(m)
            out[f"{k}:v"] = np.array(v)
        return out

    def load_state_dict(self, state):
        """Restore what :meth:`state_dict` gave (any mapping of the same
        entries, e.g. an ``.npz`` file); keys absent from ``state`` keep
        their state."""
        self.set_moments({k: (int(np.asarray(state[f"{k}:t"]).ravel()[0]), state[f"{k}:m"],
                              state[f"{k}:v"])
                          for k in self.rates if f"{k}:m" in state})
