import numpy as np
import pytest

from nrsfm import SolverError, ValidationError, solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d, rotation_error
from nrsfm.sequence import Sequence
from nrsfm.solvers import Rank3Params, available_solvers, get_solver, params_from_strings


def test_registry_lists_and_rejects():
    assert "rank3" in available_solvers()
    with pytest.raises(ValidationError, match=r"method: expected one of .*'rank3'.*got 'nope'"):
        get_solver("nope")


@pytest.mark.parametrize("cameras", ["random", "smooth"])
def test_rank3_recovers_a_rigid_object(cameras):
    seq = lowrank_sequence(60, 15, 1, cameras=cameras, seed=2)
    rec = solve(seq, "rank3")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-6
    assert e3d(rec.points_3d, seq.points_3d, frame="object", pred_rotations=rec.rotations,
               gt_rotations=seq.camera_rotations) < 1e-6
    np.testing.assert_allclose(np.linalg.det(rec.rotations), 1.0, atol=1e-9)
    assert rec.runtime_s > 0 and rec.converged and rec.params == {"min_eigenvalue": 1e-9}


def test_rank3_weak_perspective_rigid():
    seq = lowrank_sequence(40, 12, 1, seed=4)
    scales = np.linspace(0.5, 2.0, 40)[:, None, None]
    k = np.array([[1000.0, 0, 320], [0, 1000.0, 240], [0, 0, 1]])
    p2 = seq.points_2d * scales * 1000 + np.array([320.0, 240.0])
    persp = seq.replace(points_2d=p2, projection="perspective", intrinsics=k)
    rec = solve(persp, "rank3")
    shape_err = e3d(rec.points_3d / np.linalg.norm(rec.points_3d, axis=(1, 2), keepdims=True),
                    seq.points_3d / np.linalg.norm(seq.points_3d, axis=(1, 2), keepdims=True))
    assert shape_err < 1e-6


def test_rank3_refuses_missing_points_with_a_hint():
    seq = lowrank_sequence(20, 10, 1, missing=0.1, seed=1)
    with pytest.raises(SolverError, match=r"rank3: expected complete tracks, got .*% missing"):
        solve(seq, "rank3")


@pytest.mark.parametrize("case", ["planar", "three_frames", "collinear_noise"])
def test_rank3_degenerate_inputs_never_nan(case, rng):
    if case == "planar":
        shape = np.c_[rng.standard_normal((10, 2)), np.zeros(10)]
        seq = lowrank_sequence(10, 10, 1, seed=0)
        pts = np.einsum("fij,pj->fpi", seq.camera_rotations, shape)
        seq = Sequence(points_2d=pts[..., :2], points_3d=pts)
    elif case == "three_frames":
        seq = lowrank_sequence(3, 10, 1, seed=0)
    else:
        line = np.outer(rng.standard_normal(8), [1.0, 2.0])
        seq = Sequence(points_2d=np.repeat(line[None], 5, axis=0) + 1e-6 * rng.standard_normal((5, 8, 2)))
    rec = solve(seq, "rank3")
    assert np.isfinite(rec.points_3d).all()


def test_params_from_strings_coerces_and_validates():
    assert params_from_strings(Rank3Params, ["min_eigenvalue=1e-6"]).min_eigenvalue == 1e-6
    with pytest.raises(ValidationError, match="no parameter 'K'"):
        params_from_strings(Rank3Params, ["K=3"])
    with pytest.raises(ValidationError, match="expected float"):
        params_from_strings(Rank3Params, ["min_eigenvalue=abc"])
    with pytest.raises(ValidationError, match="NAME=VALUE"):
        params_from_strings(Rank3Params, ["min_eigenvalue"])
    with pytest.raises(ValidationError, match=r"min_eigenvalue: expected a value in \(0, 1\)"):
        Rank3Params(min_eigenvalue=2.0)
    seq = lowrank_sequence(10, 6, 1)
    for name in ("csf2", "pr", "empnd"):  # NaN passes every per-class check ("tol >= 0" is false for it)
        with pytest.raises(ValidationError, match=rf"{get_solver(name).params.__name__}.tol: expected a finite"):
            solve(seq, name, params_from_strings(get_solver(name).params, ["tol=nan"]))


def test_solve_checks_keyword_parameters_before_building_them():
    from nrsfm.solvers import CSF2Params

    seq = lowrank_sequence(30, 10, 2, seed=1)
    for value, got in (("12", "str '12'"), (2.5, "float 2.5"), (True, "bool True")):  # raised TypeError inside
        with pytest.raises(ValidationError, match=f"CSF2Params.K: expected int, got {got}"):
            solve(seq, "csf2", K=value)
    with pytest.raises(ValidationError, match="CSF2Params has no parameter 'KK'; known: \\['K', "):
        solve(seq, "csf2", KK=3)
    assert solve(seq, "csf2", K=np.int64(2), tol=0).params["K"] == 2  # numpy integers, and ints for floats
    # a params object and keywords: the keywords replace its fields (they were silently ignored)
    assert solve(seq, "csf2", CSF2Params(d=5), K=2).params == {**vars(CSF2Params(d=5)), "K": 2}
    with pytest.raises(ValidationError, match="params: expected CSF2Params, got Rank3Params"):
        solve(seq, "csf2", Rank3Params(), K=2)


# ------------------------------------------------------------------ PR
def test_pr_recovers_a_noise_free_low_rank_sequence():
    seq = lowrank_sequence(200, 30, 3, seed=0)
    rec = solve(seq, "pr")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    np.testing.assert_allclose(rec.points_3d[..., :2], seq.points_2d - seq.points_2d.mean(1, keepdims=True),
                               atol=1e-9)  # reprojection is exact
    np.testing.assert_allclose(np.linalg.det(rec.rotations), 1.0, atol=1e-9)


def test_pr_with_missing_points():
    seq = lowrank_sequence(120, 25, 3, seed=1, missing=0.2)
    rec = solve(seq, "pr")
    assert e3d(rec.points_3d, seq.points_3d) < 5e-3


def test_lowrank_fit_finds_the_rank_with_missing_entries(rng):
    from nrsfm.solvers.base import lowrank_fit

    # rank 6 plus a translation per row, nearly rigid (the last three singular values 1% of the first)
    w = (rng.standard_normal((200, 6)) * [1, 1, 1, .01, .01, .01]) @ rng.standard_normal((6, 30))
    w += rng.standard_normal((200, 1))
    mask = np.repeat(rng.random((100, 30)) > 0.2, 2, axis=0)
    assert lowrank_fit(w, mask, 6)[0] < 1e-6
    residual, factor = lowrank_fit(w, mask, 3)
    assert residual > 1e-3 and factor.shape == (3, 30)
    np.testing.assert_allclose(factor @ factor.T, np.eye(3), atol=1e-12)
    assert lowrank_fit(w, mask, 6, start=factor)[0] < 1e-6  # warm-started from the rank-3 fit


def test_auto_k_leaves_the_factorisation_short_of_w():
    """3K = 2F makes the rank-3K factorisation all of W, which leaves the cameras free: three frames of a K = 2
    sequence gave CSF2 e3D 17.0 with K = 2."""
    from nrsfm.solvers.csf2 import auto_k

    assert auto_k(lowrank_sequence(3, 15, 2, seed=1).measurement_matrix()) == 1
    assert auto_k(lowrank_sequence(4, 15, 2, seed=1).measurement_matrix()) == 2
    assert auto_k(lowrank_sequence(40, 9, 2, seed=1).measurement_matrix()) == 2  # 3K < P as well


def test_auto_k_with_missing_points_matches_complete_tracks():
    """Nearly rigid tracks (the face, rank 7) with 20% missing get the complete tracks' K, not the cap (8)."""
    from nrsfm.datasets.synthetic import face_sequences
    from nrsfm.solvers.csf2 import auto_k

    complete = face_sequences(1, 60)[0]
    seq = face_sequences(1, 60, missing=0.2)[0]
    mask = np.repeat(seq.weights > 0, 2, axis=0)
    assert auto_k(complete.measurement_matrix()) == auto_k(seq.measurement_matrix(), mask) == 4
    rng = np.random.default_rng(0)  # exact rank 5, nearly rigid (like the shark): K = 3
    w = (rng.standard_normal((400, 5)) * np.geomspace(1, 3e-3, 5)) @ rng.standard_normal((5, 50))
    assert auto_k(w) == auto_k(w + rng.standard_normal((400, 1)), np.repeat(rng.random((200, 50)) > .25, 2, 0)) == 3
    noisy = lowrank_sequence(60, 30, 2, noise=0.01, missing=0.2, seed=0)  # no exact rank; the noise floor's: 6
    assert auto_k(noisy.measurement_matrix(), np.repeat(noisy.weights > 0, 2, axis=0)) == 2
    # PR imputes and starts with that K, not with CSF2's rule on the (full-rank) completion
    rec = solve(seq, "pr", max_iter=1)
    assert rec.info["init_K"] == 4 and rec.info["impute_rank"] == 12


def test_exact_completion_of_noise_free_tracks():
    """The 150-frame face (rank 7) with 20% missing: the rank ladder reaches the exact rank-7 fit (before session
    30's gauge-free steps it stalled there, residual > 1e-4, and fitted 8, whose completion is not unique); the
    fill is the true W. CSF2 then matches its complete-track result."""
    from nrsfm.datasets.synthetic import face_sequences
    from nrsfm.solvers.base import complete_lowrank, lowrank_fit, visible_rank

    seq, complete = face_sequences(4, 150, missing=0.2)[0], face_sequences(4, 150)[0]
    w, truth = seq.measurement_matrix(), complete.measurement_matrix()
    mask = np.repeat(seq.weights > 0, 2, axis=0)
    factor = None
    for rank in range(1, 8):  # the ladder alone
        residual, factor = lowrank_fit(w, mask, rank, start=factor)
    assert residual < 1e-8
    rank, b = visible_rank(w, mask, 18)
    assert rank == 7 and b.shape == (7, w.shape[1])
    filled, how = complete_lowrank(w, mask, 12, (rank, b))
    assert how == "exact"
    assert np.abs(filled - truth).max() < 1e-4 * np.abs(truth).max()
    rec, ref = solve(seq, "csf2"), solve(complete, "csf2")
    assert rec.info["completion"] == "exact" and rec.info["K"] == ref.info["K"] == 4
    assert abs(e3d(rec.points_3d, seq.points_3d) - e3d(ref.points_3d, complete.points_3d)) < 1e-4


def test_exact_completion_needs_every_point_seen_often_enough():
    from nrsfm.solvers.base import complete_lowrank

    seq = lowrank_sequence(60, 20, 2, seed=0)  # noise-free, rank 6 after centring
    w = seq.measurement_matrix()
    mask = np.ones_like(w, dtype=bool)
    assert complete_lowrank(w, mask, 6)[1] == "exact"
    mask[2:, 0] = False  # point 0 seen in one frame only: its column of the factor is not fixed
    filled, how = complete_lowrank(w, mask, 6)
    assert how == "imputed" and np.isfinite(filled).all()


def test_noisy_tracks_are_imputed_not_forced_to_a_rank():
    seq = lowrank_sequence(60, 30, 2, noise=0.01, missing=0.2, seed=0)
    w, mask = seq.measurement_matrix(), np.repeat(seq.weights > 0, 2, axis=0)
    from nrsfm.solvers.base import complete_lowrank

    filled, how = complete_lowrank(w, mask, 6)
    assert how == "imputed" and np.isfinite(filled).all()
    np.testing.assert_array_equal(filled[mask], w[mask])
    assert solve(seq, "pr", max_iter=1).info["completion"] == "imputed"


@pytest.mark.parametrize("case", ["rigid", "three_frames", "planar"])
def test_pr_degenerate_inputs_never_nan(case, rng):
    if case == "rigid":
        seq = lowrank_sequence(30, 10, 1, seed=0)
    elif case == "three_frames":
        seq = lowrank_sequence(3, 10, 2, seed=0)
    else:
        shape = np.c_[rng.standard_normal((10, 2)), np.zeros(10)]
        rot = lowrank_sequence(10, 10, 1, seed=0).camera_rotations
        pts = np.einsum("fij,pj->fpi", rot, shape)
        seq = Sequence(points_2d=pts[..., :2], points_3d=pts)
    rec = solve(seq, "pr", max_iter=30)
    assert np.isfinite(rec.points_3d).all()
    if case == "rigid":
        assert e3d(rec.points_3d, seq.points_3d) < 1e-3


def test_pr_centred_log_det_gradient_matches_finite_differences(central_differences):
    import torch

    from nrsfm.procrustes import align, align_vjp, log_det_and_gradient

    rng = np.random.default_rng(3)
    x = torch.as_tensor(rng.standard_normal((1, 6, 3, 7)))

    def value(x):
        a = align(x, tol=1e-13).aligned
        return log_det_and_gradient(a - a.mean(dim=1, keepdim=True), 0.05)[0].sum().item()

    al = align(x, tol=1e-13)
    g = log_det_and_gradient(al.aligned - al.aligned.mean(dim=1, keepdim=True), 0.05)[1]
    grad = align_vjp(g - g.mean(dim=1, keepdim=True), al)
    fd = central_differences(value, x)
    torch.testing.assert_close(grad, fd, atol=1e-6, rtol=1e-5)


def test_pr_paper_formulation_stays_available():
    seq = lowrank_sequence(60, 12, 2, seed=2)
    rec = solve(seq, "pr", regulariser="nuclear", centre=False, init="rigid")
    assert rec.info["init"] == "rigid" and np.isfinite(rec.points_3d).all()
    with pytest.raises(ValidationError, match="regulariser: expected one of logdet, nuclear"):
        solve(seq, "pr", regulariser="trace")


def test_pr_on_yoga_reaches_csf2_accuracy_or_better(cmu_dir):
    from nrsfm.datasets.cmu import load_cmu_mat

    seq = load_cmu_mat(cmu_dir / "yoga.mat")
    rec = solve(seq, "pr")
    # the log-det regulariser from CSF2's start: .0192 (CSF2 .0304; the paper's nuclear norm from the rigid
    # start .58); benchmarks/RESULTS.md
    assert rec.info["init"] == "csf2"
    assert e3d(rec.points_3d, seq.points_3d) < 0.025


def test_pr_with_missing_points_starts_from_the_occlusion_aware_csf2(cmu_dir):
    """On dance's first 100 frames with 20% missing, the rank-3K imputation is far off where a point is missing
    long; PR from CSF2 on the imputed tracks gave e3D 1.68 (``start_rounds=0``), from the occlusion-aware
    CSF2 .178."""
    from benchmarks.classic import drop_entries
    from nrsfm.datasets.cmu import load_cmu_mat

    seq = drop_entries(load_cmu_mat(cmu_dir / "dance.mat").select_frames(np.arange(100)), 0.2)
    rec = solve(seq, "pr")
    assert rec.info["init"] == "csf2-occlusion" and rec.info["completion"] == "imputed"
    assert e3d(rec.points_3d, seq.points_3d) < 0.25


def test_pr_refuses_a_frame_without_points():
    seq = lowrank_sequence(10, 8, 2, seed=0)
    vis = np.ones((10, 8))
    vis[4] = 0
    with pytest.raises(SolverError, match="frame 4 has fewer than 3 visible points"):
        solve(seq.replace(visibility=vis), "pr")


# ------------------------------------------------------------------ CSF2
def test_csf2_recovers_a_noise_free_low_rank_sequence():
    seq = lowrank_sequence(200, 30, 3, seed=0, cameras="random")
    rec = solve(seq, "csf2", K=3, d=100)
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    assert rec.info["camera_residual"] < 1e-10  # exact cameras from the complementary rank-3 space


def test_auto_k_finds_the_rank_of_noisy_low_rank_tracks():
    """Noisy tracks have full numerical rank; the automatic K used to take its cap (8) there, which on a smooth
    camera gave CSF2 e3D .61. The noise threshold finds the rank; a spectrum without a gap keeps the cap."""
    from nrsfm.datasets.synthetic import face_sequences
    from nrsfm.solvers.base import noise_rank
    from nrsfm.solvers.csf2 import auto_k

    seq = lowrank_sequence(150, 30, 3, cameras="smooth", seed=2, noise=0.01)
    w = seq.measurement_matrix()
    s = np.linalg.svd(w - w.mean(axis=1, keepdims=True), compute_uv=False)
    assert s[-2] > 1e-3 * s[0] and noise_rank(s, w.shape) == 9
    rec = solve(seq, "csf2")
    assert rec.info["K"] == 3 and e3d(rec.points_3d, seq.points_3d) < 0.05
    assert e3d(solve(seq, "csf2", K=8).points_3d, seq.points_3d) > 0.3
    assert auto_k(face_sequences(1, 120, noise=0.005)[0].measurement_matrix()) == 4  # rank 7: one more
    # a spectrum that decays without a gap (like motion capture) is not low rank plus noise: the cap
    rng = np.random.default_rng(0)
    full = (rng.standard_normal((400, 40)) * np.geomspace(1, 1e-4, 40)) @ rng.standard_normal((40, 41))
    s = np.linalg.svd(full - full.mean(axis=1, keepdims=True), compute_uv=False)
    assert noise_rank(s, full.shape) == 0 and auto_k(full) == 8
    assert noise_rank(np.zeros(5), (10, 6)) == noise_rank(np.ones(1), (2, 2)) == 0
    # rank 6 of 9: the median is the signal's and the first count (3) falls short; the median beyond it disagrees
    w = lowrank_sequence(30, 10, 2, seed=0).measurement_matrix()
    w = w + 0.01 * np.sqrt(((w - w.mean(axis=1, keepdims=True)) ** 2).mean()) * rng.standard_normal(w.shape)
    s = np.linalg.svd(w - w.mean(axis=1, keepdims=True), compute_uv=False)
    assert noise_rank(s, w.shape) == 0 and auto_k(w) == 3  # its gap (1.65) alone would pass


def test_noise_visible_rank_finds_the_noise_floor_with_missing_points():
    """Noisy tracks with missing points have no exact rank; the automatic K took its cap (8) there. The ladder of
    fits shows the rank where the pseudo singular values fall to a flat floor; without a floor it gives 0."""
    from nrsfm.solvers.base import noise_visible_rank

    seq = lowrank_sequence(150, 30, 3, cameras="smooth", seed=2, noise=0.01, missing=0.2)
    w, mask = seq.measurement_matrix(), np.repeat(seq.weights > 0, 2, axis=0)
    assert noise_visible_rank(w, mask, 18) == 9
    rec = solve(seq, "csf2")  # auto_k: 9 = 3K
    assert rec.info["K"] == 3 and e3d(rec.points_3d, seq.points_3d) < 0.05
    assert e3d(solve(seq, "csf2", K=8).points_3d, seq.points_3d) > 0.3
    rng = np.random.default_rng(1)
    mask = np.repeat(rng.random((100, 40)) > 0.2, 2, axis=0)
    w = (rng.standard_normal((200, 5)) * np.geomspace(1, 0.05, 5)) @ rng.standard_normal((5, 40))
    assert noise_visible_rank(w + 0.01 * rng.standard_normal(w.shape), mask, 18) == 5  # nearly rigid, like the shark
    decay = (rng.standard_normal((200, 30)) * np.geomspace(1, 1e-3, 30)) @ rng.standard_normal((30, 40))
    assert noise_visible_rank(decay, mask, 18) == 0  # decays without a floor (motion capture): no rank
    assert noise_visible_rank(rng.standard_normal((200, 40)), mask, 18) == 0  # noise alone: no gap
    assert noise_visible_rank(w, mask, 3) == 0  # too few ranks to see a floor beyond the gap


def test_noise_visible_rank_does_not_depend_on_rounding():
    """The ladder's fits must be minima, not wherever 30 iterations stopped: perturbed by 1e-13 of each entry (as
    another BLAS or thread count rounds), these 5%-noise tracks of rank 12 gave ranks 9, 8, 11 before the
    Levenberg-Marquardt steps left the gauge out (``benchmarks/RESULTS.md``, session 30)."""
    from benchmarks.auto_k import make_sequence
    from nrsfm.solvers.base import noise_visible_rank

    seq = make_sequence("smooth:4:3:0.05", 0.2)
    w, mask = seq.measurement_matrix(), np.repeat(seq.weights > 0, 2, axis=0)
    ranks = [noise_visible_rank(w * (1 + 1e-13 * np.random.default_rng(p).standard_normal(w.shape)), mask, 18)
             for p in range(3)]
    assert ranks == [11, 11, 11]


def test_csf2_occlusion_ranks_the_shape_starts_on_the_visible_entries():
    """With 20% missing the residual start fits the imputed W only .7% better than the authors' start (under
    ``start_margin``) but ends at e3D .04 where that one ends at .84; on a synthetic face the residual start refines
    better on the visible entries but ends worse, and five probe rounds keep the authors' start
    (``benchmarks/RESULTS.md``, session 34)."""
    from benchmarks.auto_k import make_sequence

    seq = make_sequence("smooth:4:2:0.01", 0.2)
    rec = solve(seq, "csf2", K=4)
    assert rec.info["shape_start"] == "residual (visible entries)"
    assert e3d(rec.points_3d, seq.points_3d) < 0.1
    authors = solve(seq, "csf2", K=4, residual_start=False)
    assert e3d(authors.points_3d, seq.points_3d) > 0.5
    face = make_sequence("face:0.005", 0.2)
    assert solve(face, "csf2", K=5, camera_rounds=0).info["shape_start"] == "residual (visible entries)"
    rec = solve(face, "csf2", K=5)
    assert rec.info["shape_start"] == "identity"
    assert e3d(rec.points_3d, face.points_3d) < 0.01


def test_csf2_in_pixel_units_and_with_the_automatic_k():
    seq = lowrank_sequence(120, 25, 2, seed=1, cameras="random")
    pixels = seq.replace(points_2d=500 * seq.points_2d + 320.0, points_3d=500 * seq.points_3d)
    rec = solve(pixels, "csf2", d=60)
    assert rec.info["K"] == 2  # rank 6 -> ceil(6 / 3), 3 divides it
    assert rec.converged and e3d(rec.points_3d, pixels.points_3d) < 1e-3


def test_csf2_second_shape_start_rescues_a_short_nearly_rigid_face():
    from nrsfm.datasets.synthetic import face_sequences

    seq = face_sequences(3, 150)[2]  # exact cameras from step 1; X = I stops in a poor minimum of the shape step
    authors = solve(seq, "csf2", residual_start=False, random_starts=0)
    rec = solve(seq, "csf2", random_starts=0)
    assert authors.info["shape_start"] == "identity" and e3d(authors.points_3d, seq.points_3d) > 0.5
    assert rec.info["shape_start"] == "residual" and rec.info["rmse"] < 0.9 * authors.info["rmse"]
    assert e3d(rec.points_3d, seq.points_3d) < 0.01


def test_csf2_random_shape_start_rescues_a_poor_minimum_of_both_deterministic_starts():
    seq = lowrank_sequence(300, 41, 4, cameras="smooth", seed=1, name="smooth:4:1:0")  # as in benchmarks.auto_k
    without = solve(seq, "csf2", random_starts=0)
    rec = solve(seq, "csf2")
    assert rec.info["K"] == without.info["K"] == 4
    assert without.info["shape_start"] in ("identity", "residual") and e3d(without.points_3d, seq.points_3d) > 0.2
    assert rec.info["shape_start"].startswith("random") and rec.info["rmse"] < 0.5 * without.info["rmse"]
    assert e3d(rec.points_3d, seq.points_3d) < 0.01


def test_csf2_random_start_is_kept_only_below_random_accept():
    seq = lowrank_sequence(300, 41, 4, cameras="smooth", seed=1, name="smooth:4:1:0")
    rec = solve(seq, "csf2", random_accept=0.1)  # the random start's fit, 0.18 of the RMSE, is not low enough
    assert rec.info["shape_start"] in ("identity", "residual")
    with pytest.raises(ValidationError, match="random_accept"):
        solve(seq, "csf2", random_accept=0.0)


def test_csf2_gauss_newton_decreases_the_column_space_cost_to_zero_on_exact_data():
    from nrsfm.solvers.csf2 import camera_rows, fit_shape_gn

    seq = lowrank_sequence(100, 20, 2, seed=2, cameras="smooth")
    w = seq.measurement_matrix()
    wc = w - w.mean(axis=1, keepdims=True)
    rows, cost, _ = camera_rows(wc)
    assert cost < 1e-12
    x, basis, it, converged, rmse = fit_shape_gn(wc, rows, 2, 100)  # d = F: the trajectories are in the basis
    assert converged and rmse < 1e-5 * np.sqrt((wc**2).mean())
    np.testing.assert_allclose(x.T @ x, np.eye(2), atol=1e-10)  # QR-orthonormalised


def test_csf2_occlusion_aware_and_auto_rank():
    seq = lowrank_sequence(150, 30, 2, seed=3, cameras="random", missing=0.2)
    rec = solve(seq, "csf2", d=75)
    assert rec.info["K"] >= 2
    assert e3d(rec.points_3d, seq.points_3d) < 0.02


def test_csf2_occlusion_rounds_return_their_lowest_rmse_round(monkeypatch):
    from nrsfm.datasets.synthetic import face_sequences
    from nrsfm.solvers import csf2

    seen, refine, run_rounds, start = [], csf2._refine_masked, csf2._occlusion_rounds, []

    def recording(*args):
        out = refine(*args)
        seen.append(out[2])
        return out

    def marking(*args):  # the camera rounds proper (not the shape starts' probes) begin here
        if args[7] == csf2.CSF2Params.camera_rounds:
            start.append(len(seen))
        return run_rounds(*args)

    monkeypatch.setattr(csf2, "_refine_masked", recording)
    monkeypatch.setattr(csf2, "_occlusion_rounds", marking)
    # noisy tracks: imputed, then refined in rounds (noise-free ones are completed exactly and need no rounds)
    seq = face_sequences(4, 150, noise=1e-3, missing=0.2)[0]
    rec = solve(seq, "csf2", round_iter_alt=0)
    assert rec.info["completion"] == "imputed"
    rounds = seen[start[0]:]  # the calls before are the refinements of the shape starts (and their probes)
    assert len(rounds) > 10 and rounds[-1] > min(rounds)  # the RMSE rose again before the rounds stopped
    # the rounds see W in units of a power of two (csf2's docstring, "Units"), so this product is exact
    unit = csf2.power_of_two_unit(seq.measurement_matrix(), np.repeat(seq.visibility > 0, 2, axis=0))
    assert unit == 32.0 and rec.info["rmse"] == min(rounds) * unit
    assert rec.info["rounds"] == {"20": len(rounds)}


def test_csf2_dct_basis_is_orthonormal():
    from nrsfm.solvers.csf2 import dct_basis

    b = dct_basis(50, 10)
    np.testing.assert_allclose(b.T @ b, np.eye(10), atol=1e-12)
    assert np.ptp(b[:, 0]) < 1e-12


def test_csf2_dct_weighted_gram_equals_the_direct_sum():
    from nrsfm.solvers.csf2 import dct_basis, dct_weighted_gram

    rng = np.random.default_rng(0)
    omega, weights = dct_basis(57, 9), rng.standard_normal((57, 3, 3))
    np.testing.assert_allclose(dct_weighted_gram(weights, 9), np.einsum("fa,fb,fkl->abkl", omega, omega, weights),
                               atol=1e-13)
    from nrsfm.solvers.csf2 import dct_weighted_gram_blocks

    blocks = dct_weighted_gram(weights, 9).transpose(0, 2, 1, 3).reshape(27, 27)
    np.testing.assert_array_equal(dct_weighted_gram_blocks(weights, 9), blocks)  # the same values, to the bit


def test_masked_lstsq_matches_per_point_least_squares():
    from nrsfm.solvers.base import masked_lstsq

    rng = np.random.default_rng(3)
    a, b = rng.standard_normal((40, 2, 6)), rng.standard_normal((40, 2, 5))
    vis = (rng.random((40, 5)) > 0.3).astype(float)
    vis[:, 4] = 1.0  # one point seen in every frame
    got = masked_lstsq(a, b, vis, ridge=0.0)
    for p in range(5):
        seen = vis[:, p] > 0
        want = np.linalg.lstsq(a[seen].reshape(-1, 6), b[seen, :, p].ravel(), rcond=None)[0]
        np.testing.assert_allclose(got[:, p], want, atol=1e-10)
    np.testing.assert_allclose(masked_lstsq(a, b, np.ones((40, 5)), ridge=0.0),
                               np.linalg.lstsq(a.reshape(80, 6), b.reshape(80, 5), rcond=None)[0], atol=1e-10)


def test_csf2_round_race_stops_only_the_follower_that_falls_behind():
    import threading
    import time

    from nrsfm.solvers.csf2 import _RoundRace

    race = _RoundRace(0.02, 30)
    assert not race.behind(20, 9.0)  # before race_from: no comparison, no wait
    race.post(30, 1.0)
    assert race.behind(30, 1.03) and not race.behind(30, 1.01)
    # the follower waits for the leader's post of the same round, so the outcome does not depend on timing
    threading.Thread(target=lambda: (time.sleep(0.2), race.post(40, 1.0))).start()
    assert race.behind(40, 1.5)
    race.end()
    assert not race.behind(50, 9.0)  # the leader stopped before round 50: nothing to compare with
    assert not _RoundRace(0.02, 0).behind(30, 9.0)  # race_from = 0: no race


def test_csf2_camera_refinement_recovers_cameras_from_visible_entries():
    from scipy.spatial.transform import Rotation

    from nrsfm.solvers.csf2 import _refine_cameras

    rng = np.random.default_rng(1)
    n_frames, n_points = 20, 12
    shapes = rng.standard_normal((n_frames, 3, n_points))
    rot = Rotation.random(n_frames, random_state=2).as_matrix()
    t = rng.standard_normal((n_frames, 2))
    w = (rot[:, :2] @ shapes + t[:, :, None]).reshape(2 * n_frames, n_points)
    vis = rng.random((n_frames, n_points)) > 0.3
    vis[:, :4] = True  # at least four points per frame
    start = rot @ Rotation.from_rotvec(0.2 * rng.standard_normal((n_frames, 3))).as_matrix()
    new_rot, new_t = _refine_cameras(w, np.repeat(vis, 2, axis=0), start, shapes, t + 0.3, steps=8)
    np.testing.assert_allclose(new_rot, rot, atol=1e-8)
    np.testing.assert_allclose(new_t, t, atol=1e-8)


def test_csf2_refuses_too_large_k():
    with pytest.raises(SolverError, match="3K <= min"):
        solve(lowrank_sequence(10, 8, 1, seed=0), "csf2", K=4)
    with pytest.raises(SolverError, match="d >= K"):  # X (d, K) has orthonormal columns
        solve(lowrank_sequence(40, 30, 2, seed=0), "csf2", K=6, d=5)


# ------------------------------------------------------------------ SPM
def test_spm_shape_steps_agree_on_a_small_problem():
    from nrsfm.solvers.spm import shape_admm, shape_cvxpy, shape_fpc

    seq = lowrank_sequence(20, 10, 2, seed=5)
    w = (seq.points_2d - seq.points_2d.mean(1, keepdims=True)).transpose(0, 2, 1)
    rot = seq.camera_rotations
    a = shape_cvxpy(w, rot)
    b = shape_fpc(w, rot, inner=2000, tol=1e-12)
    c, iterations = shape_admm(w, rot, tol=1e-8)
    assert np.abs(a - b).max() < 1e-4 * np.abs(a).max()
    assert np.abs(a - c).max() < 1e-4 * np.abs(a).max()
    assert iterations < 5000


@pytest.mark.parametrize("shape", [(40, 9), (9, 40)])
def test_singular_value_threshold_matches_the_svd(shape):
    from nrsfm.solvers.spm import singular_value_threshold

    rng = np.random.default_rng(1)
    m = rng.standard_normal((shape[0], 3)) @ rng.standard_normal((3, shape[1])) * 5 + rng.standard_normal(shape)
    u, s, vt = np.linalg.svd(m, full_matrices=False)
    t = float(np.median(s))  # keeps some singular values and zeroes others
    np.testing.assert_allclose(singular_value_threshold(m, t), (u * np.maximum(s - t, 0)) @ vt, atol=1e-10)
    kept = np.maximum(s - t, 0)
    kept[:2] = s[:2]  # the partial sum's proximal map leaves the 2 largest alone
    np.testing.assert_allclose(singular_value_threshold(m, t, keep=2), (u * kept) @ vt, atol=1e-10)


def test_spm_automatic_k_takes_the_rank_of_noise_free_tracks():
    """The energy rule gave K = 2 on this noise-free K = 3 sequence (its third basis shape moves little), and
    cameras 10 degrees off; the rank gives 3 and exact cameras. Noisy (full-rank) tracks keep the energy rule."""
    from nrsfm.solvers.spm import auto_rank

    def w_of(seq):
        return (seq.points_2d - seq.points_2d.mean(1, keepdims=True)).transpose(0, 2, 1).reshape(-1, seq.n_points)

    seq = lowrank_sequence(300, 17, 3, cameras="smooth", seed=0)
    assert auto_rank(w_of(seq)) == 3
    assert auto_rank(w_of(seq), rel_tol=0) == 2  # every singular value counts: the energy rule
    noisy = lowrank_sequence(300, 17, 3, cameras="smooth", seed=0, noise=0.01)
    assert auto_rank(w_of(noisy)) == auto_rank(w_of(noisy), rel_tol=0)
    rec = solve(seq, "spm")
    assert rec.info["K"] == 3 and rotation_error(rec.rotations, seq.camera_rotations) < 1e-6


def test_spm_partial_sum_recovers_a_short_arc_of_smooth_cameras():
    """A steady turn of 166 degrees over 300 frames, noise-free, exact cameras: the nuclear norm's minimum is
    another shape (e3D .33, its nuclear norm 3% below the truth's); the partial sum beyond K is zero at the
    truth and the shape step finds it."""
    seq = lowrank_sequence(300, 17, 3, cameras="smooth", seed=0)
    nuclear = solve(seq, "spm")
    partial = solve(seq, "spm", shape_objective="partial")
    assert e3d(nuclear.points_3d, seq.points_3d) > 0.1
    assert e3d(partial.points_3d, seq.points_3d) < 1e-3 and partial.converged
    assert partial.info["shape_objective"] == "partial" and partial.iterations > nuclear.iterations
    obj = np.einsum("fji,fpj->fip", partial.rotations, partial.points_3d).reshape(seq.n_frames, -1)
    sv = np.linalg.svd(obj, compute_uv=False)
    assert sv[3:].sum() < 1e-3 * sv[:3].sum()
    with pytest.raises(ValidationError, match="shape_objective"):
        solve(seq, "spm", shape_objective="rank")


def test_spm_admm_reaches_a_lower_nuclear_norm_than_the_truth():
    """Noisy shapes of a rank-2 model: the minimiser's nuclear norm is at most the ground truth's."""
    from nrsfm.solvers.spm import shape_admm

    seq = lowrank_sequence(60, 15, 2, seed=3, cameras="random")
    gt = seq.points_3d - seq.points_3d.mean(1, keepdims=True)
    gt = gt + 0.05 * np.random.default_rng(0).standard_normal(gt.shape) * gt.std()
    w = gt[..., :2].transpose(0, 2, 1)
    rot = seq.camera_rotations  # (F, 3, 3)

    def nuclear(depth):
        cam = np.concatenate([w, depth[:, None, :]], axis=1)
        return np.linalg.norm(np.einsum("fji,fjp->fip", rot, cam).reshape(len(w), -1), "nuc")

    depth, _ = shape_admm(w, rot, tol=1e-6)
    assert nuclear(depth) <= nuclear(gt[..., 2]) + 1e-6


def test_spm_chooses_cvxpy_by_the_side_of_its_semidefinite_block():
    """cvxpy's nuclear norm is a semidefinite block of side F + 3P: 5 x 60 (900 entries of S#, side 185) took
    279 s under the old limit on the entries (1000); ADMM takes milliseconds."""
    assert solve(lowrank_sequence(10, 10, 2, seed=0), "spm").info["shape_solver"] == "cvxpy"  # side 40
    rec = solve(lowrank_sequence(5, 60, 1, seed=0), "spm")
    assert rec.info["shape_solver"] == "admm" and rec.runtime_s < 10


def test_spm_recovers_low_rank_with_camera_jumps():
    seq = lowrank_sequence(30, 12, 2, seed=0, cameras="random")  # independent cameras: every frame "jumps"
    rec = solve(seq, "spm", shape_solver="cvxpy")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    assert rec.info["camera_residual"] < 1e-12


def test_spm_camera_refinement_lowers_the_nuclear_norm_and_keeps_exact_cameras():
    from nrsfm.solvers.spm import camera_step, refine_cameras_nuclear, shape_admm

    exact = lowrank_sequence(60, 20, 2, seed=0)
    rec = solve(exact, "spm", refine_cameras=True)
    assert rec.info["refined_cameras"] and e3d(rec.points_3d, exact.points_3d) < 1e-3
    seq = lowrank_sequence(40, 15, 2, seed=1, noise=0.01)
    wf = (seq.points_2d - seq.points_2d.mean(1, keepdims=True)).transpose(0, 2, 1)  # (F, 2, P)
    cameras = camera_step(wf.reshape(-1, seq.n_points), 2)

    def nuclear(rot):  # the shape step's minimum for these cameras
        depth, _ = shape_admm(wf, rot, tol=1e-7)
        cam = np.concatenate([wf, depth[:, None]], axis=1)
        return np.linalg.norm(np.einsum("fji,fjp->fip", rot, cam).reshape(len(wf), -1), "nuc"), depth

    before, depth = nuclear(cameras.rotations)
    rot = refine_cameras_nuclear(wf, cameras, depth, weight=0.0, iters=100)
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-10)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-10)
    assert nuclear(rot)[0] < before * (1 - 1e-4)  # 29.856 -> 29.842
    with pytest.raises(ValidationError, match="refine_weight >= 0"):
        solve(seq, "spm", refine_cameras=True, refine_weight=-1.0)


def test_spm_sign_resolution_does_not_use_temporal_order():
    from nrsfm.solvers.spm import resolve_signs

    seq = lowrank_sequence(40, 10, 1, seed=2, cameras="random")
    truth = seq.camera_rotations
    flip = np.diag([-1.0, -1.0, 1.0])
    rng = np.random.default_rng(0)
    flipped = truth.copy()
    bad = rng.random(40) < 0.5
    flipped[bad] = flip @ truth[bad]
    mirror = np.diag([1.0, 1.0, -1.0])  # the reference lives in a mirrored, rotated object frame
    from scipy.spatial.transform import Rotation

    h = Rotation.random(random_state=1).as_matrix() @ mirror
    reference = np.einsum("fij,jk->fik", truth, h)
    fixed = resolve_signs(flipped, reference)
    np.testing.assert_allclose(fixed, truth, atol=1e-9)


# ------------------------------------------------------------------ consensus
def test_consensus_recovers_a_noise_free_low_rank_sequence_and_says_what_it_ran():
    seq = lowrank_sequence(60, 15, 2, seed=1)
    rec = solve(seq, "consensus")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    assert rec.info["methods"] == ["empnd", "pr"] and rec.info["weights"] == [0.85, 0.15]
    assert rec.iterations == sum(rec.info["component_iterations"]) and np.isfinite(rec.rotations).all()
    missing = lowrank_sequence(60, 15, 2, seed=1, missing=0.2)
    assert e3d(solve(missing, "consensus").points_3d, missing.points_3d) < 0.02


def test_consensus_average_undoes_depth_flips_per_frame_and_weights_the_shapes():
    from nrsfm.solvers import Reconstruction, average_reconstructions
    from nrsfm.geometry import complete_rotation

    rng = np.random.default_rng(0)
    x = rng.normal(size=(6, 9, 3))
    x -= x.mean(axis=1, keepdims=True)
    rots = complete_rotation(np.linalg.qr(rng.normal(size=(6, 3, 3)))[0][:, :2])
    delta = np.zeros_like(x)
    delta[..., 2] = 0.01 * rng.normal(size=(6, 9))  # a depth change small enough to keep the signs
    delta -= delta.mean(axis=1, keepdims=True)
    flip = np.array([1.0, 1.0, -1.0])
    other, other_rots = x + delta, rots.copy()
    other[[1, 4]] *= flip  # two frames reflected in depth, their cameras D R D
    other_rots[[1, 4]] = rots[[1, 4]] * flip[:, None] * flip[None, :]
    recs = [Reconstruction(x + 5.0, rots, "a"), Reconstruction(other, other_rots, "b")]
    shapes, rotations, flipped = average_reconstructions(recs, [0.75, 0.25])
    assert flipped == 2
    np.testing.assert_allclose(shapes, x + 0.25 * delta, atol=1e-12)
    np.testing.assert_allclose(rotations, rots, atol=1e-12)
    assert average_reconstructions([recs[0], Reconstruction(x, None, "c")], [0.5, 0.5])[1] is None
    # cameras half a turn apart sum to a singular matrix: the projection still gives a proper rotation
    half_turn = rots @ np.diag([-1.0, -1.0, 1.0])
    mean_rots = average_reconstructions([recs[0], Reconstruction(x, half_turn, "d")], [0.5, 0.5])[1]
    np.testing.assert_allclose(mean_rots @ mean_rots.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (6, 3, 3)),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(mean_rots), 1.0, atol=1e-9)


def test_consensus_computes_the_shared_csf2_start_once(monkeypatch):
    import nrsfm.solvers.csf2 as csf2

    seq = lowrank_sequence(40, 12, 2, seed=3, noise=0.01, missing=0.2)
    kw = dict(camera_rounds=3, round_iter=5, round_iter_alt=0)
    alone = csf2.csf2_start(seq, 0, **kw)
    k = solve(seq, "csf2", **kw).info["K"]
    np.testing.assert_array_equal(csf2.csf2_start(seq, k, **kw), alone)  # the automatic K's start is K's
    calls = []
    real = csf2.solve_csf2.__wrapped__

    def counted(s, params):
        calls.append(params)
        return real(s, params)

    monkeypatch.setattr(csf2.solve_csf2, "__wrapped__", counted)
    with csf2.shared_starts():
        first = csf2.csf2_start(seq, 0, **kw)
        first[:] = 0.0  # a copy: the cached start is untouched
        np.testing.assert_array_equal(csf2.csf2_start(seq, k, **kw), alone)
        np.testing.assert_array_equal(csf2.csf2_start(seq, 0, **kw), alone)
        assert len(calls) == 1
        csf2.csf2_start(seq, 0, camera_rounds=4, round_iter=5, round_iter_alt=0)  # other settings: solved again
        assert len(calls) == 2
    csf2.csf2_start(seq, 0, **kw)  # the cache ended with the block
    assert len(calls) == 3
    calls.clear()
    ranks = []
    real_rank = csf2.noise_visible_rank
    monkeypatch.setattr(csf2, "noise_visible_rank", lambda *a, **kw: ranks.append(real_rank(*a, **kw)) or ranks[-1])
    solve(seq, "consensus")  # EM-PND's start with missing points is PR's occlusion-aware start
    assert sum(c.camera_rounds == 50 and c.round_iter == 5 for c in calls) == 1
    assert len(ranks) == 1  # PR's automatic K and CSF2's (in pixels / a power of two) share the noise rank
    solve(seq, "csf2", **kw)
    assert len(ranks) == 2  # outside the consensus: computed again


def test_consensus_refuses_bad_settings_and_names_itself_in_component_errors():
    from nrsfm.solvers import ConsensusParams

    with pytest.raises(ValidationError, match="two or more registered solvers"):
        ConsensusParams(methods="empnd")
    with pytest.raises(ValidationError, match="method: expected one of"):
        ConsensusParams(methods="empnd,nope")
    with pytest.raises(ValidationError, match="expected 2 non-negative numbers"):
        ConsensusParams(weights="1,-1")
    with pytest.raises(ValidationError, match="comma-separated numbers"):
        ConsensusParams(weights="a,b")
    with pytest.raises(SolverError, match="^consensus: spm: expected complete tracks"):
        solve(lowrank_sequence(30, 10, 2, seed=0, missing=0.1), "consensus", methods="empnd,spm", weights="1,1")


# ------------------------------------------------------------------ EM-PND (PND2) and EM-PPCA
def test_empnd_recovers_a_noise_free_low_rank_sequence():
    seq = lowrank_sequence(200, 30, 3, seed=0)
    rec = solve(seq, "empnd")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    assert np.isfinite(rec.rotations).all() and rec.iterations >= 2


def test_empnd_starts_from_another_solver():
    seq = lowrank_sequence(60, 15, 2, seed=3)
    for init in ("spm", "pr"):
        rec = solve(seq, "empnd", init=init)
        assert rec.info["init"] == init and e3d(rec.points_3d, seq.points_3d) < 1e-3, init
    with pytest.raises(ValidationError, match="init='spm' needs every point visible"):
        solve(lowrank_sequence(30, 10, 2, seed=0, missing=0.1), "empnd", init="spm")
    with pytest.raises(ValidationError, match="init: expected one of"):
        solve(seq, "empnd", init="c3dpo")


def test_empnd_with_missing_points_and_degenerate_frames():
    seq = lowrank_sequence(120, 25, 2, seed=2, missing=0.2)
    rec = solve(seq, "empnd")
    assert e3d(rec.points_3d, seq.points_3d) < 0.02
    vis = np.ones((10, 8))
    vis[3, :6] = 0
    with pytest.raises(SolverError, match="frame 3 has fewer than 3 visible points"):
        solve(lowrank_sequence(10, 8, 2, seed=0).replace(visibility=vis), "empnd")
    three = solve(lowrank_sequence(3, 10, 2, seed=0), "empnd", max_iter=20)
    assert np.isfinite(three.points_3d).all()


def test_empnd_cuts_the_csf2_start_short_with_missing_points(monkeypatch):
    import nrsfm.solvers.empnd as empnd

    seen = {}

    def start(seq, k, **overrides):
        seen.update(overrides, K=k)
        return seq.points_3d + 0.01

    monkeypatch.setattr(empnd, "csf2_start", start)
    seq = lowrank_sequence(60, 12, 2, seed=4, missing=0.1)
    solve(seq, "empnd", init_rounds=7, init_K=2, max_iter=3)
    assert seen == {"camera_rounds": 7, "round_iter": 5, "round_iter_alt": 0, "K": 2}
    with pytest.raises(ValidationError, match="init_rounds: expected >= 0, got -1"):
        solve(seq, "empnd", init_rounds=-1)


def test_pick_device_refuses_unknown_names_and_absent_gpus():
    import torch

    from nrsfm.device import pick_device

    assert pick_device("cpu").type == "cpu"
    assert pick_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValidationError, match="expected 'auto', 'cpu', 'cuda' or 'cuda:N', got 'tpu'"):
        pick_device("tpu")
    with pytest.raises(ValidationError, match="expected 'auto', 'cpu'"):
        pick_device("meta")
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ValidationError, match="asked for, but torch sees"):
        pick_device(f"cuda:{count}" if count else "cuda")
    with pytest.raises(ValidationError, match="asked for, but torch sees"):  # refused before any work
        params_from_strings(get_solver("empnd").params, [f"device=cuda:{count}" if count else "device=cuda"])


def test_empnd_runs_where_it_is_asked_and_says_so():
    import torch

    seq = lowrank_sequence(60, 12, 2, seed=4, missing=0.1)
    cpu = solve(seq, "empnd", device="cpu", max_iter=15)
    assert cpu.info["device"] == "cpu" and cpu.info["start_s"] > 0
    if not torch.cuda.is_available():
        pytest.skip("no CUDA GPU here: the GPU half of this test needs one")
    for complete in (False, True):  # DensePosterior and CompletePosterior
        s = seq.replace(visibility=np.ones_like(seq.weights)) if complete else seq
        a = solve(s, "empnd", device="cpu", max_iter=15)
        b = solve(s, "empnd", device="cuda", max_iter=15)
        assert b.info["device"].startswith("cuda") and b.iterations == a.iterations
        np.testing.assert_allclose(b.points_3d, a.points_3d, atol=1e-6 * np.abs(a.points_3d).max())


def test_factorisation_start_is_exact_on_a_rigid_object_and_keeps_the_tracks():
    from nrsfm.solvers.rectify import factor_rotations, factorisation_start

    rigid = lowrank_sequence(60, 15, 1, seed=3)
    start = factorisation_start(rigid.points_2d)
    assert e3d(start, rigid.points_3d) < 1e-8  # rigid: the trace-minimising depths are the true ones
    w = rigid.points_2d - rigid.points_2d.mean(axis=1, keepdims=True)
    np.testing.assert_allclose(start[..., :2], w, atol=1e-10)
    with pytest.raises(SolverError, match="every track is constant"):
        factorisation_start(np.zeros((5, 6, 2)))
    # the recovered camera rows are the true ones up to one global orthogonal matrix and a sign per frame:
    # their inner products with frame 0's rows agree up to that sign
    rot, scale, k = factor_rotations(w.transpose(0, 2, 1).reshape(-1, 15))
    assert k == 3 and scale.min() == 1.0
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-10)
    est, true = rot[:, :, :2].transpose(0, 2, 1), rigid.camera_rotations[:, :2]  # (F, 2, 3)
    e0, t0 = est @ est[0].T, true @ true[0].T
    sign = np.sign(np.einsum("fij,fij->f", e0, t0))
    np.testing.assert_allclose(e0, sign[:, None, None] * t0, atol=1e-8)


def test_rank3_rectification_drives_the_orthonormality_residual_down():
    from nrsfm.solvers.rectify import OrthonormalityConstraints, rectify_fista, rectify_rank

    seq = lowrank_sequence(40, 12, 2, seed=5)
    w = seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)
    u = np.linalg.svd(w.transpose(0, 2, 1).reshape(-1, 12), full_matrices=False)[0]
    con3 = OrthonormalityConstraints(u[:, :3])
    _, g = rectify_fista(con3, np.eye(3) / 3)
    con6 = OrthonormalityConstraints(u[:, :6])
    start = np.zeros((6, 3))
    start[:3, : g.shape[1]] = g
    before = con6.cost(start @ start.T / np.linalg.norm(start) ** 2)[0]
    gg, g6 = rectify_rank(con6, start, max_iter=5000)
    assert con6.cost(gg)[0] < 1e-5 * before and g6.shape == (6, 3)
    assert abs(np.trace(gg) - 1) < 1e-12 and np.linalg.eigvalsh(gg).min() > -1e-12


@pytest.mark.parametrize("k", [5, 8])  # 10 frames: K^2 = 25 <= 4F uses the Gram matrix, 64 > 4F the factor
def test_orthonormality_constraints_gram_form_equals_the_direct_residual(k):
    import torch

    from nrsfm.solvers.rectify import OrthonormalityConstraints

    u3 = np.linalg.qr(np.random.default_rng(0).standard_normal((20, k)))[0]
    con = OrthonormalityConstraints(u3)
    assert (con._factor is None) == (k == 5)
    gg = np.random.default_rng(1).standard_normal((k, k))
    gg = gg @ gg.T
    a, b = u3[0::2], u3[1::2]
    direct = np.concatenate([np.einsum("fi,ij,fj->f", a, gg, a) - np.einsum("fi,ij,fj->f", b, gg, b),
                             2 * np.einsum("fi,ij,fj->f", a, gg, b)])
    cost, half_grad = con.cost(gg)
    assert abs(cost * con.lipschitz - direct @ direct) < 1e-9 * (direct @ direct)
    g_t = torch.from_numpy(gg).requires_grad_(True)
    at, bt = torch.from_numpy(a), torch.from_numpy(b)
    res = torch.cat([((at @ g_t) * at).sum(1) - ((bt @ g_t) * bt).sum(1), 2 * ((at @ g_t) * bt).sum(1)])
    (grad,) = torch.autograd.grad((res**2).sum(), g_t)  # over symmetric GG: its symmetric part
    np.testing.assert_allclose(2 * half_grad * con.lipschitz, (grad + grad.T).numpy() / 2, rtol=1e-9, atol=1e-12)
    # the scale is the largest eigenvalue of E^T E: a power iteration gets no higher
    x = np.random.default_rng(2).standard_normal(k * k)
    for _ in range(200):
        x = con.cost(x.reshape(k, k))[1].ravel()
        x /= np.linalg.norm(x)
    assert abs(float(con.cost(x.reshape(k, k))[0]) - 1.0) < 1e-6


def test_unit_trace_psd_projection():
    from nrsfm.solvers.rectify import project_unit_trace_psd

    gg, g = project_unit_trace_psd(np.diag([3.0, 1.0, 0.5, -1.0]))
    np.testing.assert_allclose(np.diag(gg), [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    gg, g = project_unit_trace_psd(np.diag([0.5, 0.4, 0.3, 0.2]), rank=3)
    np.testing.assert_allclose(np.sort(np.diag(gg))[::-1], [0.4333333333, 0.3333333333, 0.2333333333, 0.0],
                               atol=1e-9)
    assert g.shape == (4, 3) and abs(np.trace(gg) - 1) < 1e-12


def test_empnd_probe_keeps_the_start_with_the_lower_cost():
    seq = lowrank_sequence(60, 12, 2, seed=6)
    rec = solve(seq, "empnd", probe_iter=5, max_iter=30)
    costs = rec.info["probe_costs"]
    assert len(costs) == 2 and rec.info["init"] == ("factorisation", "csf2")[int(np.argmin(costs))]
    assert np.isfinite(rec.points_3d).all() and rec.iterations <= 30
    assert solve(seq, "empnd", max_iter=3, probe_iter=0).info["init"] == "factorisation"
    with pytest.raises(ValidationError, match="needs every point visible"):
        solve(lowrank_sequence(20, 10, 2, seed=0, missing=0.2), "empnd", init="factorisation")


def test_empnd_probes_both_starts_on_noise_free_tracks_only():
    from nrsfm.solvers.empnd import exactly_low_rank

    # a camera turning steadily about one axis: the factorisation start alone ends at e3D .086
    smooth = lowrank_sequence(300, 20, 3, cameras="smooth", seed=0)
    assert exactly_low_rank(smooth)
    rec = solve(smooth, "empnd")
    assert rec.info["probe_costs"] is not None and rec.info["init"] == "csf2"
    assert e3d(rec.points_3d, smooth.points_3d) < 0.02
    noisy = lowrank_sequence(40, 12, 2, seed=1, noise=1e-3)
    assert not exactly_low_rank(noisy)
    rec = solve(noisy, "empnd", max_iter=5)
    assert rec.info["probe_costs"] is None and rec.info["init"] == "factorisation"


def _pnd_problem(rng, n: int, q: int, spread: float):
    """A random EM-PND state: mean `(3, q)`, alignment, a precision with the PND null space, complete data."""
    import torch

    from nrsfm.solvers.empnd import align, constrained_directions

    mu0 = torch.from_numpy(rng.standard_normal((1, 3, q)) + spread * rng.standard_normal((n, 3, q)))
    mean = mu0.mean(dim=0)
    mean = mean / mean.norm()
    sr, s = align(mu0, mean)
    nb = constrained_directions(mean)
    proj = torch.eye(3 * q, dtype=torch.float64) - nb @ nb.T
    a = torch.from_numpy(rng.standard_normal((3 * q, 3 * q)))
    data = torch.from_numpy(rng.standard_normal((n, 3, q)))
    data[:, 2] = 0.0
    obs = torch.eye(q, dtype=torch.float64).expand(n, q, q).contiguous()
    return mean, sr, s, proj @ (a @ a.T) @ proj, data, obs


def test_pnd_cost_gradient_matches_finite_differences():
    import torch

    from nrsfm.solvers.empnd import DensePosterior, pnd_cost

    rng = np.random.default_rng(0)
    mean, sr, s, lam, data, obs = _pnd_problem(rng, 12, 6, 0.2)
    post = DensePosterior(lam, sr, data, obs, 1e-2)
    m_var = mean.clone().requires_grad_(True)
    cost, _ = pnd_cost(m_var, post.mu, post.moment)
    (grad,) = torch.autograd.grad(cost, m_var)
    direction = torch.from_numpy(rng.standard_normal(mean.shape))
    eps = 1e-6
    with torch.no_grad():
        fd = (pnd_cost(mean + eps * direction, post.mu, post.moment)[0]
              - pnd_cost(mean - eps * direction, post.mu, post.moment)[0]) / (2 * eps)
    assert abs(float(fd) - float((grad * direction).sum())) < 1e-6 * max(1.0, abs(float(fd)))


def test_empnd_complete_posterior_matches_the_dense_one():
    import torch

    from nrsfm.solvers.empnd import CompletePosterior, DensePosterior, align

    rng = np.random.default_rng(1)
    mean, sr, s, lam, data, obs = _pnd_problem(rng, 15, 7, 0.1)
    dense, fast = DensePosterior(lam, sr, data, obs, 1e-3), CompletePosterior(lam, sr, s, data, 1e-3)
    torch.testing.assert_close(fast.mu, dense.mu, rtol=1e-9, atol=1e-9)
    assert abs(fast.trace - dense.trace) < 1e-9 * dense.trace
    sr2, _ = align(dense.mu, mean + 0.05 * torch.from_numpy(rng.standard_normal(mean.shape)))
    torch.testing.assert_close(fast.moment(sr2), dense.moment(sr2), rtol=1e-9, atol=1e-9)


def test_empnd_rotated_block_sum_from_six_blocks_matches_the_kronecker_sum():
    import torch

    from nrsfm.solvers.empnd import _rotated_block_sum, _upper_blocks, _upper_gram_blocks

    rng = np.random.default_rng(2)
    n, q = 7, 5
    factor = torch.from_numpy(rng.standard_normal((n, q + 1, 3 * q)))
    mats = factor.transpose(1, 2) @ factor  # (F, 3q, 3q) symmetric
    rot = torch.from_numpy(rng.standard_normal((n, 3, 3)))  # any 3x3, not only rotations
    kron = torch.stack([torch.kron(r, torch.eye(q, dtype=torch.float64)) for r in rot])
    expected = (kron @ mats @ kron.transpose(1, 2)).sum(dim=0)
    torch.testing.assert_close(_rotated_block_sum(rot, _upper_blocks(mats, q), q), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(_upper_gram_blocks(factor, q), _upper_blocks(mats, q), rtol=1e-12, atol=1e-12)


def test_emppca_recovers_a_noise_free_low_rank_sequence_and_handles_missing_points():
    seq = lowrank_sequence(200, 30, 3, seed=0)
    assert e3d(solve(seq, "emppca", K=3).points_3d, seq.points_3d) < 1e-3
    seq = lowrank_sequence(120, 25, 2, seed=2, missing=0.2)
    assert e3d(solve(seq, "emppca", K=2).points_3d, seq.points_3d) < 0.02


def _degenerate(case: str) -> Sequence:
    rng = np.random.default_rng(0)
    if case == "rigid":
        return lowrank_sequence(12, 9, 1, seed=4)
    if case == "planar":
        shape = np.c_[rng.standard_normal((10, 2)), np.zeros(10)]
        pts = np.einsum("fij,pj->fpi", lowrank_sequence(10, 10, 1, seed=0).camera_rotations, shape)
        return Sequence(points_2d=pts[..., :2], points_3d=pts)
    if case == "three_frames":  # 6 rows: a rank-3K factorisation with K = 2 fits W exactly
        return lowrank_sequence(3, 10, 2, seed=0)
    if case == "three_frames_four_points":  # EM-PND's factorisation start raised numpy's LinAlgError here
        return lowrank_sequence(3, 4, 2, seed=304)
    if case == "static_camera":  # one frame repeated: no 3D information at all
        return Sequence(points_2d=np.repeat(lowrank_sequence(10, 10, 1, seed=0).points_2d[:1], 10, axis=0))
    if case == "collinear":  # one line in every frame, scaled at random (EM-PND raised torch's LinAlgError)
        line = np.c_[np.linspace(0, 1, 8), np.linspace(0, 2, 8)]
        return Sequence(points_2d=line[None] * np.random.default_rng(1).random((10, 1, 1)))
    if case == "coincident":  # every frame's points at one place (CSF2 and EM-PPCA raised numpy's ValueError)
        return Sequence(points_2d=np.repeat(rng.standard_normal((10, 1, 2)), 8, axis=1))
    vis = np.ones((30, 12))
    if case == "point_never_visible":
        vis[:, 4] = 0
    else:
        vis[5] = 0  # "frame_all_missing"
    return lowrank_sequence(30, 12, 2, seed=0).replace(visibility=vis)


@pytest.mark.parametrize("case", ["rigid", "planar", "three_frames", "three_frames_four_points", "static_camera",
                                  "collinear", "coincident", "frame_all_missing", "point_never_visible"])
def test_every_solver_gives_finite_shapes_or_a_clear_error_on_degenerate_input(case):
    """The issue's degenerate inputs, for every registered solver: finite shapes and cameras, or an NRSfMError
    whose message names the solver (never NaN, never a bare error from a library underneath); a rigid sequence
    is always solved."""
    from nrsfm.errors import NRSfMError

    seq = _degenerate(case)
    for name in available_solvers():
        try:
            rec = solve(seq, name)
        except NRSfMError as err:
            assert case != "rigid", f"{name} refused a rigid sequence: {err}"
            assert str(err).startswith(f"{name}:"), (name, str(err))
            continue
        assert rec.points_3d.shape == (seq.n_frames, seq.n_points, 3), name
        assert np.isfinite(rec.points_3d).all() and np.isfinite(rec.rotations).all(), name
        if case in ("coincident", "frame_all_missing", "point_never_visible"):
            raise AssertionError(f"{name} solved a sequence with {case.replace('_', ' ')}")


def test_every_solver_refuses_tracks_without_extent():
    """Every frame's visible points at one place (here also with points missing): one shared message."""
    from nrsfm.solvers import get_solver

    complete = _degenerate("coincident")
    missing = complete.replace(points_2d=np.where(np.arange(8)[None, :, None] == 3, np.nan, complete.points_2d),
                               visibility=np.arange(8)[None].repeat(10, 0) != 3)
    for name in available_solvers():
        for seq in (complete, missing) if get_solver(name).handles_missing else (complete,):
            with pytest.raises(SolverError, match=rf"^{name}: the visible points of every frame of .* coincide"):
                solve(seq, name)


def test_solvers_of_orthographic_tracks_refuse_perspective_ones_with_the_fix():
    from nrsfm.datasets.synthetic import human_sequences
    from nrsfm.solvers import get_solver

    seq = human_sequences(("S9",), ("turning",), (1,), n_frames=30, projection="perspective")[0]
    for name in available_solvers():
        if get_solver(name).handles_perspective:
            assert np.isfinite(solve(seq, name).points_3d).all(), name
            continue
        with pytest.raises(SolverError, match=rf"^{name}: expected orthographic tracks, got perspective .*"
                                              r"seq\.to_weak_perspective\(\)"):
            solve(seq, name)
        assert np.isfinite(solve(seq.to_weak_perspective(), name).points_3d).all(), name


def test_a_point_never_visible_is_refused_with_the_fix():
    seq = _degenerate("point_never_visible")
    with pytest.raises(SolverError, match=r"point 4 is visible in no frame.*select_points"):
        solve(seq, "csf2")
    kept = seq.select_points(seq.visibility.any(axis=0))
    assert kept.n_points == 11 and np.isfinite(solve(kept, "csf2").points_3d).all()


def test_every_solver_refuses_two_frames():
    """Two orthographic views leave even a rigid shape's depths free (a rotation about one axis): every solver
    returned e3D .27-8.5 on a rigid 2 x 15 sequence before, against .0000 from three frames."""
    seq = lowrank_sequence(2, 15, 1, seed=1)
    for name in available_solvers():
        with pytest.raises(SolverError, match=rf"^{name}: expected at least 3 frames, got 2"):
            solve(seq, name)
        assert e3d(solve(lowrank_sequence(3, 15, 1, seed=1), name).points_3d,
                   lowrank_sequence(3, 15, 1, seed=1).points_3d) < 1e-3, name


def test_every_solver_refuses_three_points():
    """A triangle is planar: rank3, CSF2, SPM and EM-PPCA returned shapes with e3D .9-5.5 before."""
    seq = lowrank_sequence(20, 3, 1, seed=1)
    for name in available_solvers():
        with pytest.raises(SolverError, match=rf"^{name}: expected at least 4 points, got 3"):
            solve(seq, name)


@pytest.mark.parametrize("name", ["rank3", "csf2", "spm", "pr", "empnd", "emppca", "consensus"])
def test_solvers_do_not_depend_on_the_units_of_the_tracks(name):
    """The same noise-free sequence in units 1e5 and 1e-7 times smaller or larger: the same e3D (CSF2 gave .98
    at 1e5 and EM-PPCA, which starts from it, .86, against .044 and .0000 at 1, before its tracks were
    normalised)."""
    seq = lowrank_sequence(40, 15, 2, seed=1)
    errors = []
    for scale in (1.0, 1e5, 1e-7):
        scaled = seq.replace(points_2d=seq.points_2d * scale, points_3d=seq.points_3d * scale)
        errors.append(e3d(solve(scaled, name).points_3d, scaled.points_3d))
    assert max(errors) - min(errors) < 1e-3, errors


def test_large_arrays_on_heap_is_scoped_and_harmless():
    import platform

    from nrsfm._malloc import large_arrays_on_heap

    with large_arrays_on_heap() as ok:
        big = np.ones(40 << 17)  # 40 MiB, above glibc's default mmap threshold
        assert big.sum() == big.size
    assert ok == (platform.system() == "Linux" and platform.libc_ver()[0] == "glibc")
