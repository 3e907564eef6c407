"""Penalized weighted least squares on tets (``fit --model absorption``'s
default solver): the exact total variation of the tets' linear field, its
separable surrogate, the solver against a general-purpose bounded
optimizer (scipy's L-BFGS-B) on the same objective with the projector
written out as a matrix, and one-row scans whose slab ties its two vertex
layers."""
import numpy as np
import pytest

from mi_tetvr.mesh.initial import grid_init
from mi_tetvr.recon.synthetic import make_xray_dataset
from mi_tetvr.recon.tomography import (PenalizedLS, Projector, TetGradient, depths,
                                       statistical_weights, tied_unknowns)


@pytest.fixture(scope="module")
def mesh():
    v, t = grid_init(np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), 4, jitter=0.25, seed=2)
    from mi_tetvr.mesh.topology import build_topology
    return v, build_topology(v, t).tets


def test_gradient_is_exact_for_linear_fields_and_tv_is_its_integral(mesh):
    """A linear field's gradient is its slope in every tet (closed form), and
    its total variation the slope's norm times the box's volume."""
    v, t = mesh
    a = np.array([0.3, -1.2, 0.7])
    grad = TetGradient(v, t)
    g = (grad.G @ (v @ a + 0.4)).reshape(-1, 3)
    np.testing.assert_allclose(g, np.broadcast_to(a, g.shape), atol=1e-10)
    assert grad.total_variation(v @ a) == pytest.approx(np.linalg.norm(a) * 8.0, rel=1e-10)
    assert grad.volumes.sum() == pytest.approx(8.0, rel=1e-12)


def test_penalty_gradient_and_its_separable_majorizer(mesh):
    """The smooth TV's gradient against central differences; the separable
    quadratic built from the curvature bound lies above the penalty (the
    surrogate's defining property), for steps small and large."""
    v, t = mesh
    grad = TetGradient(v, t)
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, len(v))
    delta = 0.3
    f0, g0, c0 = grad.penalty(x, delta)
    h = 1e-6
    for j in rng.choice(len(v), 8, replace=False):
        e = np.zeros(len(v))
        e[j] = h
        fd = (grad.penalty(x + e, delta)[0] - grad.penalty(x - e, delta)[0]) / (2 * h)
        assert g0[j] == pytest.approx(fd, rel=1e-5, abs=1e-9)
    for scale in (1e-3, 0.1, 1.0, 10.0):
        for _ in range(5):
            s = rng.normal(0, scale, len(v))
            surrogate = f0 + g0 @ s + 0.5 * np.sum(c0 * s * s)
            assert grad.penalty(x + s, delta)[0] <= surrogate * (1 + 1e-12) + 1e-15


@pytest.fixture(scope="module")
def small_problem(tmp_path_factory):
    """A 5^3-sample blob seen by 5 noisy parallel-beam views, the tet grid
    on its samples, and the projector written out as a matrix (column j:
    the depths of vertex j's hat function)."""
    from mi_tetvr.grid.volume import make_volume
    g = np.linspace(-1, 1, 5)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    vol = make_volume(np.exp(-3 * ((x - 0.2) ** 2 + y ** 2 + (z + 0.1) ** 2)))
    out = tmp_path_factory.mktemp("pwls")
    made = make_xray_dataset(vol, out, views=5, test_views=0, flux=3e3, progress=False)
    lo, hi = vol.bounds()
    s = float(vol.spacing[0])
    V, T = grid_init(np.stack([lo - 1e-4 * s, hi + 1e-4 * s]), 4)
    proj = Projector(V, T, [v.camera for v in made["train"]])
    A = np.stack([proj.forward(np.eye(len(V))[j]) for j in range(len(V))], axis=1)
    b = depths(made["train"], 3e3)
    w = statistical_weights(made["train"], 3e3)
    return V, T, proj, A, b, w


class MatrixProjector:
    """The walk's projector written out as the matrix ``A`` (rows per view at
    ``offsets``): what the solver sees of a projector, without the renders."""

    def __init__(self, A, offsets):
        self.A, self.offsets, self.n = A, offsets, A.shape[1]
        self.sensors = [None] * (len(offsets) - 1)

    rows = Projector.rows

    def forward(self, x, views=None):
        return self.A[self.rows(range(len(self.sensors)) if views is None else views)] @ x

    def adjoint(self, y, views=None):
        return self.A[self.rows(range(len(self.sensors)) if views is None else views)].T @ y


def test_pwls_reaches_the_minimum_scipy_finds(small_problem):
    """One subset per pass (no ordered-subset approximation): the solver's
    objective reaches the minimum that L-BFGS-B (scipy) finds with x >= 0 on
    the same objective, the walk's projector as an explicit matrix (for both)."""
    from scipy.optimize import minimize
    V, T, proj, A, b, w = small_problem
    grad = TetGradient(V, T)
    pls = PenalizedLS(MatrixProjector(A, proj.offsets), b, w, grad, subsets=1)
    start = pls.start(passes=2)
    lam = 0.3
    beta = lam * pls.beta0

    def objective(x):
        r = A @ x - b
        f, g, _ = grad.penalty(x, pls.delta)
        return 0.5 * np.sum(w * r * r) + beta * f, A.T @ (w * r) + beta * g

    ref = minimize(objective, start, jac=True, method="L-BFGS-B",
                   bounds=[(0, None)] * len(V), options={"maxiter": 5000, "ftol": 1e-15,
                                                        "gtol": 1e-12})
    x = pls.solve(lam, 150, start)
    f_ref, f_got = ref.fun, objective(x)[0]
    f_start = objective(start)[0]
    # within 0.1 % of the way from the start to the minimum, and near the same x
    assert f_got - f_ref <= 1e-3 * (f_start - f_ref), (f_got, f_ref, f_start)
    assert np.linalg.norm(x - ref.x) <= 0.02 * np.linalg.norm(ref.x)
    # the penalty matters here: without it the minimum is another field
    x0 = pls.solve(0.0, 150, start)
    assert np.linalg.norm(x0 - ref.x) > 0.05 * np.linalg.norm(ref.x)


def test_tied_unknowns_make_the_projector_act_on_them(small_problem):
    """With vertices tied along z, the projector is A E (E: each vertex its
    unknown's value) and its adjoint E^T A^T: checked against the explicit
    matrix; the gradient's columns are summed alike."""
    V, T, _, A, b, _ = small_problem
    tie = tied_unknowns(V)
    assert tie.max() + 1 == 25                 # a column of 5 vertices per (x, y)
    assert all(np.ptp(V[tie == k][:, :2], axis=0).max() < 1e-12 for k in range(25))
    E = np.zeros((len(V), 25))
    E[np.arange(len(V)), tie] = 1.0
    tied = Projector(V, T, small_problem[2].cameras, basis=tie)
    rng = np.random.default_rng(4)
    u = rng.uniform(0, 1, 25)
    y = rng.uniform(-1, 1, len(b))
    np.testing.assert_allclose(tied.forward(u), A @ E @ u, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(tied.adjoint(y), E.T @ A.T @ y, rtol=1e-4, atol=1e-5)
    G = TetGradient(V, T).G.toarray()
    np.testing.assert_allclose(TetGradient(V, T, tie).G.toarray(), G @ E, atol=1e-12)


def test_adaptive_mesh_puts_the_fine_grid_where_the_field_changes():
    """On a coarse grid (every other vertex of the fine one, the box grown by a
    cell along an odd axis) a field with a sharp ramp across x = 0.3: the
    split vertices are fine-grid vertices, they gather at the ramp, the count
    stays within the budget, and the field at them is the coarse mesh's
    (linear interpolation along the split edges: exact for a linear field)."""
    from mi_tetvr.mesh.initial import grid_shape
    from mi_tetvr.recon.tomography import adaptive_mesh, coarse_grid
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 0.4]])
    fine_v, _ = grid_init(box, 10)
    shape = np.asarray(grid_shape(box, 10))
    assert shape.tolist() == [10, 10, 7]
    v, t = coarse_grid(box, 10)
    cell = (box[1] - box[0]) / shape
    lattice = lambda p: np.abs((p - box[0]) / cell - np.round((p - box[0]) / cell))  # noqa: E731
    assert lattice(v).max() < 1e-9 and len(v) == 6 * 6 * 5
    assert v[:, 2].max() == pytest.approx(box[0, 2] + 8 * cell[2])    # one cell beyond
    from mi_tetvr.mesh.topology import build_topology
    t = build_topology(v, t).tets
    x = np.clip((v[:, 0] - 0.3) / 0.2, 0, 1)
    budget = len(fine_v) // 2
    v2, t2, x2, k = adaptive_mesh(v, t, x, TetGradient(v, t), budget)
    assert len(v) < len(v2) <= budget and k > 0
    new = v2[len(v):]
    assert lattice(new).max() < 1e-9
    # the new vertices sit by the ramp, and none far from it
    assert np.all(np.abs(new[:, 0] - 0.4) <= 0.5)
    # a budget under the coarse grid's count splits nothing
    v1, t1, _, k1 = adaptive_mesh(v, t, x, TetGradient(v, t), len(v) - 1)
    assert k1 == 0 and len(v1) == len(v) and len(t1) == len(t)
    linear = 0.2 + v[:, 0] - 0.5 * v[:, 1] + 0.3 * v[:, 2]
    v3, _, y3, _ = adaptive_mesh(v, t, linear, TetGradient(v, t), budget)
    np.testing.assert_allclose(y3, 0.2 + v3[:, 0] - 0.5 * v3[:, 1] + 0.3 * v3[:, 2],
                               atol=1e-12)
