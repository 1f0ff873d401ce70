"""Each energy term of ``core/terms`` alone: its gradient against central differences of its
own energy, its Hessian blocks against central differences of its own gradient, rigid
motions, and the blocks' positive semi-definiteness."""
import numpy as np
import pytest
import trimesh

from cosserat_ros.core.energy import elastic_energy
from cosserat_ros.core.model import Model
from cosserat_ros.core.terms import bending, membrane, TERMS
from cosserat_ros.core.terms.jet import model_scratch
from cosserat_ros.mesh import ClothMesh, grid_mesh
from cosserat_ros.simulator import Material

MAT = Material(zeta=20.0, xi=1e-3, phi=2e-3, density=0.2)


def _model(name):
    if name == 'icosphere':
        m = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
        return Model.from_mesh(ClothMesh(m.vertices, m.faces))
    return Model.from_mesh(grid_mesh(6, 5, pattern=name, seed=1))


def _deformed(model, amp, seed=0):
    """A smooth bend plus a little noise: every term's energy and gradient non-zero."""
    X = model.mesh.vertices
    rng = np.random.default_rng(seed)
    x = X + amp * rng.standard_normal(X.shape)
    x[:, 2] += 0.3 * amp * np.sin(3.0 * X[:, 0]) * np.cos(2.0 * X[:, 1]) / 0.02
    return x


def _rotation(seed=3):
    q, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    return q * np.sign(np.linalg.det(q))


def _assert_gradient_is_the_central_difference(t, model, coeff, x, h=1e-6):
    g = t.gradient(model, coeff, x)
    assert np.abs(g).max() > 0
    fd = np.zeros_like(x)
    for i in range(x.shape[0]):
        for k in range(3):
            xp, xm = x.copy(), x.copy()
            xp[i, k] += h
            xm[i, k] -= h
            fd[i, k] = (t.energy(model, coeff, xp) - t.energy(model, coeff, xm)) / (2 * h)
    assert np.abs(g - fd).max() <= 1e-6 * np.abs(g).max()


@pytest.mark.slow
@pytest.mark.parametrize('term', sorted(TERMS))
@pytest.mark.parametrize('name', ['regular', 'irregular', 'icosphere'])
def test_gradient_is_the_central_difference_of_the_energy(term, name):
    t, model = TERMS[term], _model(name)
    coeff = model.coefficients(MAT)
    x = _deformed(model, 0.01)
    _assert_gradient_is_the_central_difference(t, model, coeff, x)


@pytest.mark.parametrize('phi', [MAT.phi, 0.0])
@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_the_one_pass_elastic_energy_is_the_terms_sum(name, phi):
    # energy.elastic_energy (the implicit solver's line search) against each term's own
    # energy: the same fields from one vertex pass, without the coupling's when phi = 0
    model = _model(name)
    coeff = model.coefficients(Material(zeta=MAT.zeta, xi=MAT.xi, phi=phi,
                                        density=MAT.density))
    x = _deformed(model, 0.01)
    parts = [t.energy(model, coeff, x) for t in TERMS.values()]
    assert all(p != 0.0 for p in parts[:2]) and (parts[2] != 0.0) == (phi != 0.0)
    assert elastic_energy(model, coeff, x, model_scratch(model)) == pytest.approx(
        sum(parts), rel=1e-13)


def _fd_blocks(t, model, coeff, x, h=1e-6):
    """Diagonal blocks (n,3,3) of the central difference of the term's gradient."""
    n = len(x)
    out = np.zeros((n, 3, 3))
    for k in range(3):
        for i in range(n):          # one vertex at a time: its own block only
            xp, xm = x.copy(), x.copy()
            xp[i, k] += h
            xm[i, k] -= h
            d = (t.gradient(model, coeff, xp)[i] - t.gradient(model, coeff, xm)[i]) / (2 * h)
            out[i, :, k] = d
    return out


def test_membrane_blocks_are_exact_and_psd_only_clamps_compression():
    model = _model('irregular')
    coeff = model.coefficients(MAT)
    stretched = model.mesh.vertices * np.array([1.05, 1.03, 1.0])
    stretched[:, 2] += 0.02 * np.sin(4.0 * stretched[:, 0])
    for x, psd in ((stretched, True), (stretched, False), (_deformed(model, 0.01), False)):
        got = membrane.hessian_blocks(model, coeff, x, psd=psd)
        want = _fd_blocks(membrane, model, coeff, x)
        assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max()
    compressed = model.mesh.vertices * np.array([0.95, 0.97, 1.0])
    exact = membrane.hessian_blocks(model, coeff, compressed, psd=False)
    clamped = membrane.hessian_blocks(model, coeff, compressed, psd=True)
    assert np.linalg.eigvalsh(exact).min() < 0 <= np.linalg.eigvalsh(clamped).min()


def test_membrane_matrix_is_the_whole_hessian_and_its_diagonal_the_blocks():
    # the sparse d2E_m/dx2 the implicit solver factors: every column against the central
    # difference of the gradient (stretched: psd changes nothing), its diagonal blocks the
    # blocks, symmetric; compressed, psd makes it positive semi-definite
    model = _model('irregular')
    coeff = model.coefficients(MAT)
    n = model.n_vertices
    x = model.mesh.vertices * np.array([1.05, 1.03, 1.0])
    x[:, 2] += 0.02 * np.sin(4.0 * x[:, 0])
    H = membrane.hessian_matrix(model, coeff, x).toarray()
    assert np.abs(H - H.T).max() <= 1e-12 * np.abs(H).max()
    h = 1e-6
    fd = np.zeros((3 * n, 3 * n))
    for j in range(3 * n):
        xp, xm = x.copy(), x.copy()
        xp.reshape(-1)[j] += h
        xm.reshape(-1)[j] -= h
        fd[:, j] = (membrane.gradient(model, coeff, xp)
                    - membrane.gradient(model, coeff, xm)).reshape(-1) / (2 * h)
    assert np.abs(H - fd).max() <= 1e-5 * np.abs(fd).max()
    blocks = np.stack([H[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])
    assert np.abs(blocks - membrane.hessian_blocks(model, coeff, x)).max() \
        <= 1e-12 * np.abs(blocks).max()
    compressed = model.mesh.vertices * np.array([0.95, 0.97, 1.0])
    exact = membrane.hessian_matrix(model, coeff, compressed, psd=False).toarray()
    clamped = membrane.hessian_matrix(model, coeff, compressed).toarray()
    scale = np.abs(exact).max()
    assert np.linalg.eigvalsh(exact).min() < -1e-6 * scale
    assert np.linalg.eigvalsh(clamped).min() >= -1e-10 * scale


@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_compression_product_is_what_the_clamp_adds_to_the_hessian(name):
    # the implicit solver's projected Newton: add_compression_product(q) must be exactly
    # (hessian_matrix(psd) - hessian_matrix(exact)) q, zero where every face is stretched
    model = _model(name)
    coeff = model.coefficients(MAT)
    f = model.faces
    m = len(f.corners)
    rng = np.random.default_rng(4)
    q = rng.standard_normal((model.n_vertices, 3))
    tens = np.empty((m, 3))
    squeezed_x = _deformed(model, 0.002) * 0.93
    stretched_x = model.mesh.vertices * 1.04
    for x, compressed in ((squeezed_x, True), (stretched_x, False)):
        membrane.compression_stress(x, f.corners, f.dinv, f.area, coeff.zeta, tens)
        out = np.zeros_like(q)
        which = membrane.compressed_faces(tens)
        assert (len(which) > 0) == compressed
        membrane.add_compression_product(model, tens, which, q, out)
        diff = (membrane.hessian_matrix(model, coeff, x)
                - membrane.hessian_matrix(model, coeff, x, psd=False))
        want = (diff @ q.reshape(-1)).reshape(-1, 3)
        if compressed:
            assert np.abs(want).max() > 0.0
            assert np.abs(out - want).max() <= 1e-12 * np.abs(want).max()
        else:
            assert np.abs(out).max() == 0.0 and np.abs(want).max() == 0.0


@pytest.mark.parametrize('term', ['bending', 'coupling'])
@pytest.mark.parametrize('name', ['regular', 'irregular'])
def test_gauss_newton_blocks_are_exact_at_a_flat_rest_state(term, name):
    # at rest the curvature change, the strain and the jet residuals vanish, so the terms
    # that rotate the normal or carry the strain's second derivative drop out: the
    # Gauss-Newton block is the Hessian's own diagonal block there
    t, model = TERMS[term], _model(name)
    coeff = model.coefficients(MAT)
    x = model.mesh.vertices.copy()
    kw = {'psd': False} if term == 'coupling' else {}
    got = t.hessian_blocks(model, coeff, x, **kw)
    want = _fd_blocks(t, model, coeff, x, h=1e-7)
    assert np.abs(want).max() > 0
    assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max()


@pytest.mark.parametrize('name', ['regular', 'icosphere'])
def test_bending_blocks_approach_the_hessian_as_the_deformation_vanishes(name):
    # away from rest the Gauss-Newton block drops terms of the order of the deformation:
    # the gap to the finite-difference block falls about linearly with its amplitude
    model = _model(name)
    coeff = model.coefficients(MAT)
    gaps = []
    amps = (4e-3, 2e-3, 1e-3)
    for amp in amps:
        x = model.mesh.vertices + amp * np.random.default_rng(2).standard_normal((
            model.n_vertices, 3))
        got = bending.hessian_blocks(model, coeff, x)
        want = _fd_blocks(bending, model, coeff, x)
        gaps.append(np.abs(got - want).max() / np.abs(want).max())
    order = np.polyfit(np.log(amps), np.log(gaps), 1)[0]
    assert gaps[-1] < 0.1 and order > 0.7


@pytest.mark.parametrize('term', sorted(TERMS))
def test_blocks_are_positive_semidefinite_in_any_state(term):
    t, model = TERMS[term], _model('irregular')
    coeff = model.coefficients(MAT)
    for seed in range(3):
        x = _deformed(model, 0.03, seed)
        blocks = t.hessian_blocks(model, coeff, x)
        assert np.allclose(blocks, np.transpose(blocks, (0, 2, 1)), rtol=1e-12,
                           atol=1e-12 * np.abs(blocks).max())
        assert np.linalg.eigvalsh(blocks).min() >= -1e-12 * np.abs(blocks).max()


@pytest.mark.parametrize('term', sorted(TERMS))
@pytest.mark.parametrize('name', ['irregular', 'icosphere'])
def test_rigid_motions_change_nothing(term, name):
    t, model = TERMS[term], _model(name)
    coeff = model.coefficients(MAT)
    X = model.mesh.vertices
    R = _rotation()
    moved = X @ R.T + np.array([0.3, -1.2, 2.0])
    for x in (X, moved):
        assert abs(t.energy(model, coeff, x)) < 1e-20
        assert np.abs(t.gradient(model, coeff, x)).max() < 1e-12
    x = _deformed(model, 0.01)
    e, g = t.energy(model, coeff, x), t.gradient(model, coeff, x)
    x2 = x @ R.T + np.array([0.3, -1.2, 2.0])
    assert t.energy(model, coeff, x2) == pytest.approx(e, rel=1e-10)
    assert np.abs(t.gradient(model, coeff, x2) - g @ R.T).max() <= 1e-9 * np.abs(g).max()
    blocks = t.hessian_blocks(model, coeff, x)
    rotated = np.einsum('ab,nbc,dc->nad', R, blocks, R)
    assert np.abs(t.hessian_blocks(model, coeff, x2) - rotated).max() <= (
        1e-9 * np.abs(blocks).max())


def test_each_term_scales_with_its_own_constant_only():
    model = _model('irregular')
    x = _deformed(model, 0.01)
    base = {k: t.energy(model, model.coefficients(MAT), x) for k, t in TERMS.items()}
    assert all(v > 0 for k, v in base.items() if k != 'coupling') and base['coupling'] != 0
    for const, term in (('zeta', 'membrane'), ('xi', 'bending'), ('phi', 'coupling')):
        kw = {k: getattr(MAT, k) for k in ('zeta', 'xi', 'phi', 'density', 'damping')}
        kw[const] *= 0.5
        coeff = model.coefficients(Material(**kw))
        for k, t in TERMS.items():
            want = base[k] * (0.5 if k == term else 1.0)
            assert t.energy(model, coeff, x) == pytest.approx(want, rel=1e-12), (const, k)


def _area_ratios(model, x):
    """|a_1 x a_2| of every vertex's jet at x (1 at rest)."""
    j = model.jets
    r = np.empty(len(x))
    for i in range(len(x)):
        s = slice(j.ptr[i], j.ptr[i + 1])
        d = x[j.idx[s]] - x[i]
        r[i] = np.linalg.norm(np.cross(j.w[0, s] @ d, j.w[1, s] @ d))
    return r


def squeezed(X, t=0.05):
    """The sheet pressed to a fraction t of its width along y, with a bend."""
    x = X * np.array([1.0, t, 1.0])
    x[:, 2] = 0.4 * X[:, 0] ** 2 + 0.02 * X[:, 0] * X[:, 1]
    return x


@pytest.mark.parametrize('term', ['bending', 'coupling'])
def test_the_jet_gradient_is_exact_below_the_area_floor(term):
    """On the sheet pressed to 0.05 of its width every stencil's |a_1 x a_2| lies below
    constants.JET_AREA_FLOOR, where the jet's normal shortens (jet.floored_normal); the
    gradient is still the energy's."""
    from cosserat_ros.core.constants import JET_AREA_FLOOR
    t, model = TERMS[term], _model('irregular')
    coeff = model.coefficients(MAT)
    x = squeezed(model.mesh.vertices)
    assert _area_ratios(model, x).max() < JET_AREA_FLOOR
    assert _area_ratios(model, model.mesh.vertices).min() > 0.999
    _assert_gradient_is_the_central_difference(t, model, coeff, x)


@pytest.mark.parametrize('term', ['bending', 'coupling'])
def test_a_sheet_collapsed_onto_a_line_has_finite_forces(term):
    """Every stencil's tangents parallel, ``a_1 x a_2 = 0`` exactly (a sheet flattened onto
    a line, as ``set_positions`` may do): the floored normal's factor gam is s / max(r, f)
    (jet.floored_normal), finite at r = 0, where r s / (f r) was 0 / 0 and made every
    force of the stencil NaN. Both the reference gradient and the explicit step's force
    (the SIMD lanes) stay finite."""
    from cosserat_ros.core.terms.jet import floored_normal
    from cosserat_ros.simulator import ClothSimulator
    assert floored_normal(0.0, 0.0, 0.0, 0.0) == pytest.approx((0, 0, 0, 2 / _floor(), 0.5))
    t, model = TERMS[term], _model('regular')
    coeff = model.coefficients(MAT)
    x = model.mesh.vertices.copy()
    x[:, 1] = 0.0
    x[:, 2] = 0.3 * x[:, 0] ** 2
    assert np.all(np.isfinite(t.gradient(model, coeff, x)))
    sim = ClothSimulator(model.mesh, MAT, dt=1e-5, check_dt=False)
    sim.set_positions(x)
    assert np.all(np.isfinite(sim.internal_forces()))


def _floor():
    from cosserat_ros.core.constants import JET_AREA_FLOOR
    return JET_AREA_FLOOR


def _plate_deflection(n, pattern):
    """A model of the unit square and ``w = a sin(pi x) sin(pi y)`` on it (x, y in [0, 1]),
    and the Kirchhoff plate's energy of w, ``D/2 int (Delta w)^2 = D a^2 pi^4 / 2`` (its
    det term integrates to 0: w vanishes on the edge)."""
    model = Model.from_mesh(grid_mesh(n, n, pattern=pattern, seed=1))
    u = model.mesh.vertices[:, :2] + 0.5
    a = 1e-4
    w = a * np.sin(np.pi * u[:, 0]) * np.sin(np.pi * u[:, 1])
    return model, w, 6.0 * MAT.xi * a ** 2 * np.pi ** 4 / 2.0


@pytest.mark.slow
def test_plate_matrix_is_the_kirchhoff_plate_energy_with_order_two():
    """``bending.plate_matrix`` (the implicit solver's preconditioner for the bending):
    ``D/2 w^T K w`` against the plate's energy, converging as h^2 on the regular grid and
    within 3% on the irregular one (the cotangent Laplacian is not pointwise consistent on
    irregular meshes); the bending term's own energy converges to the same value."""
    err = []
    sizes = (10, 20, 40)
    for n in sizes:
        model, w, exact = _plate_deflection(n, 'regular')
        K = bending.plate_matrix(model)
        err.append(abs(3.0 * MAT.xi * w @ (K @ w) / exact - 1.0))
    order = -np.polyfit(np.log(sizes), np.log(err), 1)[0]
    assert 1.8 <= order <= 2.2 and err[-1] < 2e-3, (order, err)
    for n in (20, 40):
        model, w, exact = _plate_deflection(n, 'irregular')
        K = bending.plate_matrix(model)
        assert abs(3.0 * MAT.xi * w @ (K @ w) / exact - 1.0) < 0.03
    x = model.mesh.vertices.copy()
    x[:, 2] += w
    assert abs(bending.energy(model, model.coefficients(MAT), x) / exact - 1.0) < 0.01
