"""The image formation operator A = M·Ω·Φ·B and the FFT solver of its normal equations."""

from __future__ import annotations

import numpy as np
import pytest
from _problems import ConstantField, RadialField, latent_space, normalised_colour, spectral_model

from labkit.cfa import CFA_LAYOUTS
from labkit.errors import DataError
from reconstruction.model.image_formation import ImageFormation, build_formation
from reconstruction.model.operators import Dispersion, dot_test
from reconstruction.model.prior_terms import PRIORS, PriorTerm, SmoothnessTerm
from reconstruction.solve.solvers.active_set import inverse_block
from reconstruction.solve.solvers.fourier import REFINE_RESIDUAL, FourierSolver

SHAPE = (40, 60)


@pytest.mark.parametrize("with_phi", [False, True])
def test_dot_test(with_phi: bool) -> None:
    """⟨A x, y⟩ = ⟨x, Aᵀ y⟩ to 1e-10 with and without Φ (radial field, up to 1.5 px)."""
    model = spectral_model(RadialField(0.05)) if with_phi else None
    a = build_formation(
        latent_space(), (24, 36), "GBRG", model=model, origin=(8, 10), interpolation="bilinear"
    )
    assert (a.dispersion is not None) == with_phi
    result = dot_test(a, rng=np.random.default_rng(1))
    assert result.relative_error < 1e-10


def test_dispersion_samples_split_the_colour_matrix() -> None:
    """Σ_j C_j equals the dispersion-free colour matrix, and Φ = 0 gives the same raw image."""
    space = latent_space()
    a = build_formation(
        space,
        (20, 30),
        "RGGB",
        model=spectral_model(ConstantField((0.0, 0.0))),
        interpolation="bilinear",
    )
    np.testing.assert_allclose(a.colour_matrix, space.colour_matrix(), rtol=1e-12)
    x = np.random.default_rng(2).uniform(size=a.domain_shape)
    plain = a.without_dispersion()
    np.testing.assert_allclose(a.forward(x), plain.forward(x), rtol=1e-12)


@pytest.mark.parametrize("cfa", CFA_LAYOUTS)
@pytest.mark.parametrize("prior", ["L2", "L2L2", "Lap2", "L2+roughness", "L2+spectral"])
def test_fourier_solver_is_exact(cfa: str, prior: str) -> None:
    """(2AᵀA + Σ c DᵀD + βI) x = b is solved to a relative residual ≤ 1e-8 (with the
    spectral smoothness term ‖S I‖², whose DC differs from its other frequencies, and with
    plain ‖∇λ I‖²)."""
    rng = np.random.default_rng(3)
    c = normalised_colour()
    a = ImageFormation((32, 48), cfa, c[None])
    if prior == "L2+roughness":
        terms = [(0.3, PRIORS["L2"][0]), (0.05, SmoothnessTerm(c))]
    elif prior == "L2+spectral":
        terms = [(0.3, PRIORS["L2"][0]), (0.05, PriorTerm("spectral", 2))]
    else:
        terms = [(0.3, t) for t in PRIORS[prior]]
    solver = FourierSolver((32, 48), cfa, c, terms=terms, identity=1e-3)

    def matrix(x):
        out = 2 * a.adjoint(a.forward(x)) + 1e-3 * x
        for coefficient, term in terms:
            d = term.difference(x.shape)
            out += coefficient * d.adjoint(d.forward(x))
        return out

    x = rng.standard_normal(a.domain_shape)
    np.testing.assert_allclose(solver.apply(x), matrix(x), atol=1e-12 * np.abs(matrix(x)).max())
    b = matrix(x)
    solution = solver.solve(b)
    assert np.linalg.norm(matrix(solution) - b) / np.linalg.norm(b) < 1e-8
    # the preconditioner's single-precision solve: float64 out, close to the exact one
    # (measured 2.6–3.1e-5 relative here, float32 rounding amplified by the blocks' condition)
    single = solver.solve_single(b)
    assert single.dtype == np.float64
    assert np.linalg.norm(single - solution) / np.linalg.norm(solution) < 1e-4


def test_fourier_solver_with_a_uniform_shift_is_exact() -> None:
    """With Φ a uniform (periodic) shift, the per-frequency colour matrices make the solve exact."""
    rng = np.random.default_rng(4)
    model = spectral_model(ConstantField((0.7, -1.3), per_nm=True))
    a = build_formation(latent_space(), (32, 32), "GBRG", model=model, interpolation="bilinear")
    terms = [(0.1, PRIORS["L2"][0])]
    solver = FourierSolver((32, 32), "GBRG", a.fourier_colour(), terms=terms, identity=1e-2)
    x = rng.standard_normal(a.domain_shape)
    d = terms[0][1].difference(x.shape)
    kx = 2 * a.adjoint(a.forward(x)) + 1e-2 * x + 0.1 * d.adjoint(d.forward(x))
    assert np.linalg.norm(solver.solve(kx) - x) / np.linalg.norm(x) < 1e-8


@pytest.mark.parametrize("shape", [(2, 2), (2, 6), (6, 10), (10, 8), (12, 12)])
@pytest.mark.parametrize("shifted", [False, True])
def test_fourier_solver_half_quadruples_cover_every_frequency(
    shape: tuple[int, int], shifted: bool
) -> None:
    """The solver inverts only one quadruple of each conjugate pair and fills the rest by
    symmetry: every image size (half-sizes odd or even, the 2×2 minimum), with a constant
    or a per-frequency (uniform shift) colour matrix, K x and K⁻¹ b match the spatial K
    (1e-10 and 1e-8) and K times each impulse response is its impulse (1e-8); unrefined,
    they are the unrefined solves of the impulses (1e-12)."""
    rng = np.random.default_rng(11)
    model = spectral_model(ConstantField((0.7, -1.3), per_nm=True), shape=shape)
    a = build_formation(
        latent_space(), shape, "GBRG", model=model if shifted else None, interpolation="bilinear"
    )
    term = PRIORS["L2"][0]
    solver = FourierSolver(shape, "GBRG", a.fourier_colour(), terms=[(0.1, term)], identity=1e-2)
    d = term.difference(a.domain_shape)

    def matrix(x):
        return 2 * a.adjoint(a.forward(x)) + 1e-2 * x + 0.1 * d.adjoint(d.forward(x))

    x = rng.standard_normal(a.domain_shape)
    np.testing.assert_allclose(solver.apply(x), matrix(x), atol=1e-10 * np.abs(matrix(x)).max())
    assert np.linalg.norm(solver.solve(matrix(x)) - x) / np.linalg.norm(x) < 1e-8
    responses = solver.impulse_responses()  # (2, 2, n, rows, cols, n)
    for p, q, j in [(0, 0, 0), (1, 0, 3), (1, 1, a.domain_shape[2] - 1)]:
        impulse = np.zeros(a.domain_shape)
        impulse[p, q, j] = 1.0
        assert np.abs(matrix(responses[p, q, j]) - impulse).max() < 1e-8
        # unrefined, as the preconditioner's solve(refine=False) gives them
        unrefined = solver.impulse_responses(refine=False)[p, q, j]
        np.testing.assert_allclose(unrefined, solver.solve(impulse, refine=False), atol=1e-12)


def test_inverse_block_gathers_the_columns_of_the_inverse() -> None:
    """``inverse_block`` at k values is the (k × k) block of K̃⁻¹: each column the solve of
    a unit impulse at that value, read at the k values (1e-12), every Bayer phase and band
    represented, for a patch with a per-frequency (shifted) colour matrix."""
    rng = np.random.default_rng(4)
    shape = (10, 8)
    model = spectral_model(ConstantField((0.7, -1.3), per_nm=True), shape=shape)
    a = build_formation(latent_space(), shape, "GBRG", model=model, interpolation="bilinear")
    solver = FourierSolver(
        shape, "GBRG", a.fourier_colour(), terms=[(0.1, PRIORS["L2"][0])], identity=1e-2
    )
    flat = rng.choice(int(np.prod(a.domain_shape)), size=24, replace=False)
    index = np.unravel_index(flat, a.domain_shape)
    assert len(set(zip(index[0] % 2, index[1] % 2, strict=True))) == 4
    columns = []
    for value in flat:
        impulse = np.zeros(a.domain_shape)
        impulse.ravel()[value] = 1.0
        columns.append(solver.solve(impulse, refine=False)[index])
    expected = np.stack(columns, axis=1)
    block = inverse_block(solver.impulse_responses(refine=False), index, shape)
    np.testing.assert_allclose(block, 0.5 * (expected + expected.T), atol=1e-12)


def _radial_patch_formation() -> ImageFormation:
    """A of a 24×36 patch at (8, 10) with Φ of a radial field, bilinear sampling."""
    return build_formation(
        latent_space(),
        (24, 36),
        "GBRG",
        model=spectral_model(RadialField(0.05)),
        origin=(8, 10),
        interpolation="bilinear",
    )


@pytest.mark.parametrize("identity", [1e-9, 1e-3, 1.0])
def test_fourier_solver_blocks_match_a_direct_inverse(identity: float) -> None:
    """The blocks are inverted by the Woodbury identity (the data term is rank 4 per
    quadruple; with Φ applied in factored form), with a direct inverse where that loses
    digits (the mean at a tiny β): with Φ (a radial field), L2 and spectral smoothness,
    every block is within 1e-9 of ``np.linalg.inv`` of the same block (relative to its
    largest entry), at a ridge-sized, a small and a large β; a factored solve equals the
    dense inverse's to 1e-9."""
    from reconstruction.solve.solvers import fourier

    fourier._LOCAL.clear()
    a = _radial_patch_formation()
    terms = [(0.01, PRIORS["L2"][0]), (1e-3, PriorTerm("spectral", 2))]
    solver = FourierSolver((24, 36), "GBRG", a.fourier_colour(), terms=terms, identity=identity)
    assert solver.dispersive
    assert len(fourier._LOCAL._entries) == 2  # the priors' blocks and their inverse at β
    assert solver._factored is not None  # applied in factored form, formed here to compare
    matrix, inverse = solver._dense_blocks()
    direct = np.linalg.inv(matrix)
    scale = np.abs(direct).max(axis=(1, 2), keepdims=True)
    assert np.max(np.abs(inverse - direct) / scale) < 1e-9
    # the factored solve is the dense inverse's (one solve of a random image)
    b = np.random.default_rng(8).standard_normal((24, 36, matrix.shape[1] // 4))
    dense = solver._apply_quadruples(b, inverse=True, blocks=inverse)
    np.testing.assert_allclose(
        solver.solve(b, refine=False), dense, rtol=0, atol=1e-9 * np.abs(dense).max()
    )


def test_patches_with_phi_share_the_priors_inverse() -> None:
    """Two patches with different Φ (per-frequency colour matrices) but the same size and
    priors share R⁻¹ of the priors' blocks; each still solves its own matrix (1e-8)."""
    from reconstruction.solve.solvers import fourier

    fourier._LOCAL.clear()
    rng = np.random.default_rng(5)
    terms = [(0.1, PRIORS["L2"][0])]
    solvers = []
    for shift in [(0.7, -1.3), (-0.4, 0.9)]:
        model = spectral_model(ConstantField(shift, per_nm=True))
        a = build_formation(latent_space(), (32, 32), "GBRG", model=model, interpolation="bilinear")
        solver = FourierSolver((32, 32), "GBRG", a.fourier_colour(), terms=terms, identity=1e-2)
        x = rng.standard_normal(a.domain_shape)
        d = terms[0][1].difference(x.shape)
        kx = 2 * a.adjoint(a.forward(x)) + 1e-2 * x + 0.1 * d.adjoint(d.forward(x))
        assert np.linalg.norm(solver.solve(kx) - x) / np.linalg.norm(x) < 1e-8
        solvers.append(solver)
    assert solvers[0]._prior is solvers[1]._prior
    assert len(fourier._LOCAL._entries) == 2


def test_fourier_solver_refuses_a_singular_matrix() -> None:
    """Without β, a gradient prior leaves the mean of the 4n components at frequency 0
    undetermined beyond the 4 the mosaic observes: a DataError that says to give β > 0."""
    a = build_formation(latent_space(), (16, 16), "GBRG")
    with pytest.raises(DataError, match=r"singular.*identity > 0"):
        FourierSolver(
            (16, 16), "GBRG", a.fourier_colour(), terms=[(0.1, PRIORS["L2"][0])], identity=0.0
        )


def test_fourier_solver_refines_only_an_inaccurate_inverse() -> None:
    """Iterative refinement is taken only where the inverse's probe residual exceeds
    REFINE_RESIDUAL: well conditioned, the inverse is accurate and ``solve`` is the
    unrefined solve bit for bit; with a 1e-3 ridge alone (condition 4e6) it is not, and the
    refinement step lowers the blocks' residual (measured 2.1e-10 against 3.1e-10 on 1 and
    2 threads). The residual of the real image after the inverse FFT is not compared: it is
    set by rounding in the projection onto real images (1e-10 on one machine, 2.4e-5 on
    another, where refinement then changes it by ±1 %), not by the refinement."""
    rng = np.random.default_rng(2)
    a = build_formation(latent_space(), (16, 16), "GBRG")
    b = rng.standard_normal(a.domain_shape)

    def residual(solver: FourierSolver, x: np.ndarray) -> float:
        return float(np.linalg.norm(solver.apply(x) - b) / np.linalg.norm(b))

    prior = FourierSolver(  # block condition numbers ≤ 4e3
        (16, 16), "GBRG", a.fourier_colour(), terms=[(1.0, PRIORS["L2"][0])], identity=1.0
    )
    assert not prior._refine
    np.testing.assert_array_equal(prior.solve(b), prior.solve(b, refine=False))
    ridge = FourierSolver((16, 16), "GBRG", a.fourier_colour(), identity=1e-3)
    assert ridge._refine
    refined, unrefined = ridge.solve(b), ridge.solve(b, refine=False)
    assert not np.array_equal(refined, unrefined)
    assert REFINE_RESIDUAL < residual(ridge, refined) < 1e-3
    spectra = np.random.default_rng(3).standard_normal((2, *ridge._matrix.shape[:2], 1))
    s = spectra[0] + 1j * spectra[1]
    first = ridge._inverse @ s
    step = first + ridge._inverse @ (s - ridge._matrix @ first)  # what solve() refines

    def block_residual(y: np.ndarray) -> float:
        return float(np.linalg.norm(ridge._matrix @ y - s) / np.linalg.norm(s))

    assert block_residual(step) < 0.9 * block_residual(first)


def test_mean_translation_operator_is_what_the_fourier_solver_inverts() -> None:
    """Ã (Φ as per-sample mean translations, by FFT): ⟨Ãx, y⟩ = ⟨x, Ãᵀy⟩ to 1e-10, the FFT
    solver's matrix is 2ÃᵀÃ + βI, and for a uniform periodic shift Ã is A itself."""
    rng = np.random.default_rng(7)
    a = _radial_patch_formation()
    x = rng.standard_normal(a.domain_shape)
    y = rng.standard_normal(a.range_shape)
    forward, adjoint = a.translation_forward(x), a.translation_adjoint(y)
    assert abs(np.vdot(forward, y) - np.vdot(x, adjoint)) < 1e-10 * abs(np.vdot(forward, y))
    solver = FourierSolver((24, 36), "GBRG", a.fourier_colour(), identity=1e-2)
    expected = 2 * a.translation_adjoint(forward) + 1e-2 * x
    np.testing.assert_allclose(solver.apply(x), expected, atol=1e-10 * np.abs(expected).max())
    assert np.linalg.norm(forward - a.forward(x)) > 0.01 * np.linalg.norm(forward)  # Φ varies

    uniform = build_formation(
        latent_space(),
        (32, 32),
        "GBRG",
        model=spectral_model(ConstantField((0.7, -1.3), per_nm=True)),
        interpolation="bilinear",
    )
    x = rng.standard_normal(uniform.domain_shape)
    np.testing.assert_allclose(uniform.translation_forward(x), uniform.forward(x), atol=1e-10)
    cubic = build_formation(
        latent_space(),
        (32, 32),
        "GBRG",
        model=spectral_model(ConstantField((0.7, -1.3), per_nm=True)),
        interpolation="cubic",
    )  # the symbol follows Φ's interpolation: Keys' weights, not bilinear ones
    np.testing.assert_allclose(cubic.translation_forward(x), cubic.forward(x), atol=1e-10)
    plain = uniform.without_dispersion()
    y = rng.standard_normal(plain.range_shape)
    np.testing.assert_array_equal(plain.translation_adjoint(y), plain.adjoint(y))


def test_fourier_solver_needs_even_sizes() -> None:
    with pytest.raises(DataError, match="even"):
        FourierSolver((31, 32), "RGGB", normalised_colour())


SENSOR_MAP_NM = np.array([450.0, 500.0, 550.0, 600.0, 650.0])
SENSOR_MAP = (
    np.array(
        [
            [0.12, 1.0, 5.0],
            [0.02, 1.0, 0.85],
            [0.011, 1.0, 0.038],
            [2.6, 1.0, 0.009],
            [9.8, 1.0, 0.1],
        ]
    )
    * np.array([0.1, 0.14, 1.0, 0.13, 0.016])[:, None]
)


def sensor_map_space():
    from labkit.spectra import Spectra
    from reconstruction.model.image_formation import LatentSpace

    response = Spectra(SENSOR_MAP_NM, SENSOR_MAP, ("R", "G", "B"))
    return LatentSpace.spectral(response, SENSOR_MAP_NM)


def test_a_sensor_map_is_a_discrete_space() -> None:
    """A response tabulated at exactly the band centres (thesis Alg. 12) is the discrete model
    of Alg. 13: its colour matrix is the table itself (no integral, no overlap between bands;
    a Gaussian basis would give the 550 nm band R/G ≈ 0.18 from its neighbours instead of
    0.011), and the spectrum at the centres is the latent image."""
    space = sensor_map_space()
    assert space.kernel == "discrete"
    np.testing.assert_array_equal(space.colour_matrix(), SENSOR_MAP.T)
    x = np.random.default_rng(3).uniform(size=(4, 5, 5))
    np.testing.assert_array_equal(space.spectral_values(x), x)
    scaled = space.with_scale(np.array([1.0, 2.0, 0.5, 1.0, 3.0]))
    np.testing.assert_allclose(scaled.colour_matrix(), SENSOR_MAP.T * [1.0, 2.0, 0.5, 1.0, 3.0])


def test_each_band_of_a_sensor_map_is_warped_by_its_own_dispersion() -> None:
    """Dispersion (λ − 600)/50 px along x: whole-pixel shifts −3 … +1 px at the band centres.
    A latent image with one band set gives that band, shifted by its own shift, in its
    colours (periodic boundary: a roll), and the operator passes the dot test."""
    space = sensor_map_space()
    model = spectral_model(ConstantField((2.0, 0.0), per_nm=True))
    shape = (24, 36)
    a = build_formation(space, shape, "GBRG", model=model, interpolation="bilinear")
    plain = a.without_dispersion()
    rng = np.random.default_rng(4)
    signs = set()
    for k, wavelength in enumerate(SENSOR_MAP_NM):
        shift = round((wavelength - 600.0) / 50.0)
        x = np.zeros((*shape, SENSOR_MAP_NM.size))
        x[..., k] = rng.uniform(size=shape)
        warped = a.forward(x)
        matches = [
            sign
            for sign in (-1, 1)
            if np.allclose(warped, plain.forward(np.roll(x, sign * shift, axis=1)), atol=1e-12)
        ]
        assert matches, f"band {wavelength:g} nm is not shifted by {shift} px"
        if shift:
            signs.update(matches)
    assert len(signs) == 1  # one direction for every band
    assert dot_test(a, rng=np.random.default_rng(5)).relative_error < 1e-10
    # each sample sees only its own band: the folded matrix keeps no zero it would multiply
    assert np.count_nonzero(a._matrix.data) == a._matrix.nnz


@pytest.mark.parametrize("interpolation", ["bilinear", "cubic"])
def test_a_sensor_map_folds_phi_per_band_to_the_same_matrix(
    interpolation: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where each dispersion sample sees one band of its own, Φ's taps are laid side by
    side per raw pixel instead of going through the general route's table of (pixel,
    source) pairs: the same entries (each value to 1e-15: the weights are multiplied in
    another order), only their order within a row differs; radial dispersion up to 1.5 px,
    and a patch narrower than the stencil, where a source repeats within a row."""
    import reconstruction.model.image_formation as formation_module

    space = sensor_map_space()
    model = spectral_model(RadialField(0.05))
    own_bands = formation_module._own_bands
    for shape in [(24, 36), (2, 36)]:
        monkeypatch.setattr(formation_module, "_own_bands", own_bands)
        fast = build_formation(
            space, shape, "GBRG", model=model, origin=(8, 10), interpolation=interpolation
        )
        monkeypatch.setattr(formation_module, "_own_bands", lambda colour: None)
        general = build_formation(
            space, shape, "GBRG", model=model, origin=(8, 10), interpolation=interpolation
        )
        # a stencil wider than the patch reaches a source twice: two entries, added by products
        assert (fast._matrix.nnz > general._matrix.nnz) == (
            shape[0] < 4 and interpolation == "cubic"
        )
        canonical = fast._matrix.copy()
        canonical.sum_duplicates()
        np.testing.assert_array_equal(canonical.indptr, general._matrix.indptr)
        np.testing.assert_array_equal(canonical.indices, general._matrix.indices)
        np.testing.assert_allclose(canonical.data, general._matrix.data, rtol=1e-15, atol=1e-16)
        x = np.random.default_rng(1).random(fast.domain_shape)
        np.testing.assert_allclose(fast.forward(x), general.forward(x), rtol=1e-14)
        assert dot_test(fast, rng=np.random.default_rng(2)).relative_error < 1e-10


def test_own_bands_only_where_every_sample_sees_one_band_alone() -> None:
    from reconstruction.model.image_formation import _own_bands

    single = np.zeros((3, 3, 3))
    single[0, :, 2], single[1, 1, 0], single[2, :, 1] = 1.0, 0.5, 2.0
    np.testing.assert_array_equal(_own_bands(single), [2, 0, 1])
    shared = single.copy()
    shared[2, :, 1], shared[2, :, 2] = 0.0, 1.0  # two samples see band 2
    assert _own_bands(shared) is None
    broad = single.copy()
    broad[1, :, 1] = 0.1  # sample 1 sees two bands
    assert _own_bands(broad) is None


@pytest.mark.parametrize("boundary", ["clamp", "periodic"])
@pytest.mark.parametrize("interpolation", ["bilinear", "cubic"])
def test_the_fold_by_offsets_matches_a_sort_of_every_pair(
    interpolation: str, boundary: str
) -> None:
    """The general route keys each (raw pixel, source pixel) pair by the source's offset
    in a window round the raw pixel; it gives the matrix that a sort of every pair gives
    (``np.unique``): the same structure, and the same values to the bit with the periodic
    boundary (with ``"clamp"``, repeated border sources are added in another order, to
    1e-15), for radial dispersion up to 4 px at up to 13 samples, odd sizes and patches
    narrower than the window (which take the sort) included."""
    rng = np.random.default_rng(3)
    model = spectral_model(RadialField(0.05))
    for origin, shape in [((0, 0), (24, 36)), ((3, 40), (37, 13)), ((30, 2), (6, 40))]:
        waves = np.linspace(400.0, 700.0, 13)
        dispersion = Dispersion(
            model, waves, origin=origin, shape=shape, boundary=boundary, interpolation=interpolation
        )
        colour = rng.random((waves.size, 3, 5))
        colour[:, 0, 3] = 0.0  # a stored zero the fold must drop
        formation = ImageFormation(shape, "GBRG", colour, dispersion)
        table, sort = formation._matrix, formation._combined_by_sort(dispersion)
        np.testing.assert_array_equal(table.indptr, sort.indptr)
        np.testing.assert_array_equal(table.indices, sort.indices)
        if boundary == "periodic":
            np.testing.assert_array_equal(table.data, sort.data)
        else:
            np.testing.assert_allclose(table.data, sort.data, rtol=1e-15, atol=1e-15)
        assert np.count_nonzero(table.data) == table.nnz
