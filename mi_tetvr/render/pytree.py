"""Field-wise arithmetic on the small Dr.Jit structures of the renderer.

An optical model's per-vertex values are a ``DRJIT_STRUCT`` class (for
example color and extinction); the walk and the adjoint interpolate, clip,
add and select them without knowing their fields. These helpers map a
function over the leaves of such structures (nested structures, tuples and
lists included), so the traced arithmetic is exactly what one would write by
hand for each field.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import drjit as dr
import mitsuba as mi


def tree_map(fn: Callable[..., Any], *trees: Any) -> Any:
    """``fn`` applied leaf by leaf to structures of the same layout."""
    first = trees[0]
    fields = getattr(type(first), "DRJIT_STRUCT", None)
    if fields is not None:
        out = type(first)()
        for k in fields:
            setattr(out, k, tree_map(fn, *(getattr(t, k) for t in trees)))
        return out
    if isinstance(first, (tuple, list)):
        return type(first)(tree_map(fn, *items) for items in zip(*trees))
    return fn(*trees)


def tree_leaves(tree: Any) -> list[Any]:
    """The leaves of a structure, in field order."""
    fields = getattr(type(tree), "DRJIT_STRUCT", None)
    if fields is not None:
        return [x for k in fields for x in tree_leaves(getattr(tree, k))]
    if isinstance(tree, (tuple, list)):
        return [x for item in tree for x in tree_leaves(item)]
    return [tree]


def scalar_leaves(tree: Any) -> list[Any]:
    """The leaves of a structure with vector leaves (``Color3f``,
    ``Point3f``) split into their components, in field order: what a
    packet of floats per vertex holds."""
    out = []
    for x in tree_leaves(tree):
        out += [x[j] for j in range(len(x))] if dr.depth_v(x) > 1 else [x]
    return out


def from_scalar_leaves(template: Any, leaves: Sequence[Any]) -> Any:
    """A structure laid out as ``template`` whose components are ``leaves``
    (the inverse of :func:`scalar_leaves`)."""
    it = iter(leaves)

    def take(x):
        if dr.depth_v(x) > 1:
            return type(x)(*(next(it) for _ in range(len(x))))
        return type(x)(next(it))
    return tree_map(take, template)


def tree_copy(tree: Any) -> Any:
    """New Dr.Jit wrappers of the same values (``enable_grad`` on the copy
    leaves the original alone)."""
    return tree_map(lambda x: type(x)(x), tree)


def tree_add(a: Any, b: Any) -> Any:
    return tree_map(lambda x, y: x + y, a, b)


def tree_lerp(a: Any, b: Any, t: float | mi.Float) -> Any:
    return tree_map(lambda x, y: dr.lerp(x, y, t), a, b)


def tree_select(mask: bool | mi.Bool, a: Any, b: Any) -> Any:
    return tree_map(lambda x, y: dr.select(mask, x, y), a, b)


def tree_dot(a: Any, b: Any) -> mi.Float:
    """Sum over the leaves of their inner products (a Float per lane)."""
    total = None
    for x, y in zip(tree_leaves(a), tree_leaves(b)):
        term = dr.dot(x, y) if dr.depth_v(x) > 1 else x * y
        total = term if total is None else total + term
    return total


def weighted_sum(weights: Sequence[mi.Float], trees: Sequence[Any]) -> Any:
    """``sum_j weights[j] * trees[j]``, leaf by leaf."""
    acc = tree_map(lambda x: type(x)(0.0), trees[0])
    for w, tree in zip(weights, trees):
        acc = tree_map(lambda s, x: s + w * x, acc, tree)
    return acc
