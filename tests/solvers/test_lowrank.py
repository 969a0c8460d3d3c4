"""Low-rank fits of measurement matrices with missing entries (nrsfm.lowrank)."""

import numpy as np

from nrsfm import solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d


def test_lowrank_fit_finds_the_rank_with_missing_entries(rng):
    from nrsfm.lowrank import lowrank_fit

    # rank 6 plus a translation per row, nearly rigid (the last three singular values 1% of the first)
    w = (rng.standard_normal((200, 6)) * [1, 1, 1, .01, .01, .01]) @ rng.standard_normal((6, 30))
    w += rng.standard_normal((200, 1))
    mask = np.repeat(rng.random((100, 30)) > 0.2, 2, axis=0)
    assert lowrank_fit(w, mask, 6)[0] < 1e-6
    residual, factor = lowrank_fit(w, mask, 3)
    assert residual > 1e-3 and factor.shape == (3, 30)
    np.testing.assert_allclose(factor @ factor.T, np.eye(3), atol=1e-12)
    assert lowrank_fit(w, mask, 6, start=factor)[0] < 1e-6  # warm-started from the rank-3 fit


def test_exact_completion_of_noise_free_tracks():
    """The 150-frame face (rank 7) with 20% missing: the rank ladder reaches the exact rank-7 fit (not rank 8,
    whose completion is not unique); the fill is the true W. CSF2 then matches its complete-track result."""
    from nrsfm.datasets.synthetic import face_sequences
    from nrsfm.lowrank import complete_lowrank, lowrank_fit, visible_rank

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
    rec, ref = solve(seq, "csf2", k_rule="rank"), solve(complete, "csf2", k_rule="rank")
    assert rec.info["completion"] == "exact" and rec.info["K"] == ref.info["K"] == 4
    assert abs(e3d(rec.points_3d, seq.points_3d) - e3d(ref.points_3d, complete.points_3d)) < 1e-4


def test_exact_completion_needs_every_point_seen_often_enough():
    from nrsfm.lowrank import complete_lowrank

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
    from nrsfm.lowrank import complete_lowrank

    filled, how = complete_lowrank(w, mask, 6)
    assert how == "imputed" and np.isfinite(filled).all()
    np.testing.assert_array_equal(filled[mask], w[mask])
    assert solve(seq, "pr", max_iter=1).info["completion"] == "imputed"


def test_noise_visible_rank_finds_the_noise_floor_with_missing_points():
    """Noisy tracks with missing points have no exact rank; the automatic K took its cap (8) there. The ladder of
    fits shows the rank where the pseudo singular values fall to a flat floor; without a floor it gives 0."""
    from nrsfm.lowrank import noise_visible_rank

    seq = lowrank_sequence(150, 30, 3, cameras="smooth", seed=2, noise=0.01, missing=0.2)
    w, mask = seq.measurement_matrix(), np.repeat(seq.weights > 0, 2, axis=0)
    assert noise_visible_rank(w, mask, 18) == 9
    rec = solve(seq, "csf2", k_rule="rank")  # auto_k: 9 = 3K
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
    another BLAS or thread count rounds), these 5%-noise tracks of rank 12 give one rank: steps that include the
    gauge direction gave 9, 8 and 11."""
    from nrsfm.datasets.synthetic import drop_entries
    from nrsfm.lowrank import noise_visible_rank

    seq = drop_entries(lowrank_sequence(300, 41, 4, cameras="smooth", seed=3, noise=0.05, name="smooth:4:3:0.05"), 0.2)
    w, mask = seq.measurement_matrix(), np.repeat(seq.weights > 0, 2, axis=0)
    ranks = [noise_visible_rank(w * (1 + 1e-13 * np.random.default_rng(p).standard_normal(w.shape)), mask, 18)
             for p in range(3)]
    assert ranks == [11, 11, 11]


def test_masked_lstsq_matches_per_point_least_squares():
    from nrsfm.lowrank import masked_lstsq

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
