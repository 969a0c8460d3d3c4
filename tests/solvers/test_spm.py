"""SPM (Dai et al.)."""

import numpy as np
import pytest

from nrsfm import SolverError, ValidationError, solve
from nrsfm.datasets.synthetic import drop_entries, lowrank_sequence
from nrsfm.metrics import e3d, rotation_error


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
    rec = solve(seq, "spm", k_rule="energy")
    assert rec.info["K"] == 3 and rotation_error(rec.rotations, seq.camera_rotations) < 1e-6


def test_spm_partial_sum_recovers_a_short_arc_of_smooth_cameras():
    """A steady turn of 166 degrees over 300 frames, noise-free, exact cameras: the nuclear norm's minimum is
    another shape (e3D .33, its nuclear norm 3% below the truth's); the partial sum beyond K is zero at the
    truth and the shape step finds it."""
    seq = lowrank_sequence(300, 17, 3, cameras="smooth", seed=0)
    nuclear = solve(seq, "spm", k_rule="energy")
    partial = solve(seq, "spm", shape_objective="partial", k_rule="energy")
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
    assert solve(lowrank_sequence(10, 10, 2, seed=0), "spm", K=2).info["shape_solver"] == "cvxpy"  # side 40
    rec = solve(lowrank_sequence(5, 60, 1, seed=0), "spm", k_rule="energy")
    assert rec.info["shape_solver"] == "admm" and rec.runtime_s < 10


def test_spm_recovers_low_rank_with_camera_jumps():
    seq = lowrank_sequence(30, 12, 2, seed=0, cameras="random")  # independent cameras: every frame "jumps"
    rec = solve(seq, "spm", shape_solver="cvxpy")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    assert rec.info["camera_residual"] < 1e-12


def test_spm_camera_refinement_lowers_the_nuclear_norm_and_keeps_exact_cameras():
    from nrsfm.solvers.spm import camera_step, refine_cameras_nuclear, shape_admm

    exact = lowrank_sequence(60, 20, 2, seed=0)
    rec = solve(exact, "spm", refine_cameras=True, k_rule="energy")
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


def test_spm_default_k_is_the_agreement_rule_from_k_2():
    seq = lowrank_sequence(60, 15, 2, seed=1, noise=0.01)
    rec = solve(seq, "spm")
    dist = rec.info["agreement"]
    assert rec.info["k_rule"] == "agreement" and sorted(dist) == [2, 3, 4]  # from the energy rule's floor, 3K < P
    from nrsfm.solvers.kselect import TOLERANCE

    assert rec.info["K"] == max(k for k, d in dist.items() if d <= (1 + TOLERANCE) * min(dist.values()))
    assert solve(seq, "spm", k_rule="energy").info["k_rule"] == "energy"
    with pytest.raises(ValidationError, match="k_rule"):
        solve(seq, "spm", k_rule="rank")


def test_spm_completes_missing_points_exactly_on_noise_free_tracks():
    """Noise-free low-rank tracks with 20% of the points missing are completed exactly (rank 3K plus a translation),
    so SPM gives the shapes it gives on the complete tracks."""
    full = lowrank_sequence(60, 20, 2, seed=3, name="lr")
    missing = drop_entries(full, 0.2)
    assert not missing.is_complete
    rec = solve(missing, "spm", K=2)
    assert rec.info["completion"] == "exact" and rec.info["K"] == 2
    assert e3d(rec.points_3d, full.points_3d) < 1e-3
    assert abs(e3d(rec.points_3d, full.points_3d) - e3d(solve(full, "spm", K=2).points_3d, full.points_3d)) < 1e-4


def test_spm_imputes_noisy_tracks_and_its_energy_rule_climbs_from_its_floor():
    """With noise the completion is a hard imputation; the energy rule starts at K = 2 and stays there when the
    tracks completed at rank 6 hold their energy in 6 singular values."""
    full = lowrank_sequence(60, 20, 2, seed=3, noise=0.01, name="lr")
    rec = solve(drop_entries(full, 0.2), "spm", k_rule="energy")
    assert rec.info["completion"] == "imputed" and rec.info["K"] == 2
    assert np.isfinite(rec.points_3d).all() and e3d(rec.points_3d, full.points_3d) < 0.2


def test_spm_refuses_a_completion_with_too_few_points():
    seq = drop_entries(lowrank_sequence(30, 7, 1, seed=1, name="seven"), 0.2)
    with pytest.raises(SolverError, match=r"^spm: completing missing points at rank 3K needs 3K \+ 1 < min\(2F, P\)"):
        solve(seq, "spm", K=2)
