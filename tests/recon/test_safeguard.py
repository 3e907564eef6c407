"""Inversion safeguard of vertex-position steps (mi_tetvr.recon.safeguard)."""
import numpy as np
import pytest

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import signed_volumes
from mi_tetvr.recon.safeguard import first_root_in_unit, safe_fractions, safe_step, volume_cubic


def regular_tet():
    """A regular tet, positively oriented as (0, 1, 2, 3)."""
    return np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], float) * 0.5


# --------------------------------------------------------------------------
# cubic root finder
# --------------------------------------------------------------------------


def _roots_ref(k):
    r = np.roots(np.trim_zeros(k[::-1], "f"))
    r = r[np.abs(r.imag) < 1e-9].real
    r = r[(r > 0) & (r <= 1)]
    return r.min() if len(r) else np.inf


def test_first_root_matches_np_roots():
    rng = np.random.default_rng(1)
    k = rng.normal(size=(3000, 4))
    k[:500, 3] = 0.0                       # quadratics
    k[500:600, 2:] = 0.0                   # linear
    k[600:800] *= rng.uniform(1e-6, 1e6, (200, 1))
    got = first_root_in_unit(k)
    ref = np.array([_roots_ref(row) for row in k])
    assert np.array_equal(np.isinf(got), np.isinf(ref))
    fin = np.isfinite(ref)
    assert fin.sum() > 500
    assert np.max(np.abs(got[fin] - ref[fin])) < 1e-9
    # constructed: (s - a)(s - b)(s - c) with known roots, and a double root
    a, b, c = 0.3, 0.7, 1.5
    assert np.isclose(first_root_in_unit([-a * b * c, a * b + a * c + b * c, -(a + b + c), 1])[0],
                      0.3, atol=1e-12)
    # (s - 0.4)^2 (s + 2): touches 0 at 0.4 without crossing
    assert np.isclose(first_root_in_unit(np.polynomial.polynomial.polyfromroots(
        [0.4, 0.4, -2]))[0], 0.4, atol=1e-12)
    assert first_root_in_unit([1.0, 0, 0, 0])[0] == np.inf


def test_volume_cubic():
    v, t = grid_mesh(2, jitter=0.3, seed=0)
    d = np.random.default_rng(0).normal(size=v.shape) * 0.3
    k = volume_cubic(v, t, d)
    for s in (0.0, 0.37, 1.0):
        assert np.allclose(k @ s ** np.arange(4), 6 * signed_volumes(v + s * d, t), atol=1e-12)


# --------------------------------------------------------------------------
# safe_step
# --------------------------------------------------------------------------


@pytest.mark.parametrize("per_vertex", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_safe_step_prevents_inversion(per_vertex, seed):
    v, t = grid_mesh(5, jitter=0.2, seed=seed)
    rng = np.random.default_rng(10 + seed)
    h = 2 / 5
    d = rng.normal(size=v.shape) * h * (0.3 + 0.3 * seed)
    v0 = signed_volumes(v, t)
    assert np.all(v0 > 0)
    assert np.count_nonzero(signed_volumes(v + d, t) <= 0) > 0      # the raw step inverts
    for ratio in (0.1, 0.0):
        out, n_short, f = safe_step(v, t, d, ratio, per_vertex=per_vertex,
                                    return_factors=True)
        assert np.all((f >= 0) & (f <= 1))
        assert np.allclose(out, f[:, None] * d)
        assert n_short > 0
        v1 = signed_volumes(v + out, t)
        assert np.all(v1 > 0)
        assert np.all(v1 > 0.999 * ratio * v0)
        # the whole straight path stays valid too
        for s in np.linspace(0, 1, 9)[1:]:
            assert np.all(signed_volumes(v + s * out, t) > 0.99 * ratio * v0)
        if not per_vertex:
            assert np.all(f == f[0])
        elif seed == 0:  # moderate step: many vertices keep all of theirs
            assert np.count_nonzero(f == 1) > 0.2 * len(v)


def test_safe_step_keeps_small_steps():
    v, t = grid_mesh(4, jitter=0.2, seed=4)
    d = np.random.default_rng(3).normal(size=v.shape) * 0.002
    assert np.all(safe_fractions(v, t, d, 0.1) == 1.0)
    for per_vertex in (True, False):
        out, n_short = safe_step(v, t, d, 0.1, per_vertex=per_vertex)
        assert n_short == 0 and np.array_equal(out, d)


def test_safe_step_shortens_only_near_trouble():
    """One vertex pushed through its neighbourhood: the per-vertex mode shortens
    only vertices of the tets it would invert, the rest keep their step."""
    v, t = grid_mesh(4, jitter=0.2, seed=6)
    rng = np.random.default_rng(6)
    d = rng.normal(size=v.shape) * 0.003
    i = int(np.argmin(np.linalg.norm(v, axis=1)))              # the center vertex
    d[i] = [0.9, 0.0, 0.0]                                     # ~2 cells: inverts tets
    assert np.any(signed_volumes(v + d, t) <= 0)
    out, n_short, f = safe_step(v, t, d, 0.1, return_factors=True)
    assert np.all(signed_volumes(v + out, t) > 0)
    assert 0 < f[i] < 1
    near = np.unique(t[np.any(t == i, axis=1)])
    assert np.all(f[np.setdiff1d(np.arange(len(v)), near)] == 1)
    assert n_short <= len(near)
    # the center vertex still moves part of the way
    assert np.linalg.norm(out[i]) > 0.05


def test_safe_fractions_exact_for_single_tet():
    """A tet squashed by moving its apex straight down through the base: the
    safe fraction is exactly where the height reaches min_volume_ratio."""
    v = regular_tet()
    t = np.array([[0, 1, 2, 3]])
    if signed_volumes(v, t)[0] < 0:
        t = t[:, [0, 1, 3, 2]]
    # move vertex t[0,3] towards and through its opposite face
    a = t[0, 3]
    base = v[t[0, :3]]
    n = np.cross(base[1] - base[0], base[2] - base[0])
    n /= np.linalg.norm(n)
    height = np.dot(v[a] - base[0], n)
    d = np.zeros_like(v)
    d[a] = -2.0 * height * n                                  # lands mirrored: inverted
    s = safe_fractions(v, t, d, 0.25)[0]
    assert np.isclose(s, 0.75 / 2.0, atol=1e-12)             # height 1 - 2 s = 0.25
