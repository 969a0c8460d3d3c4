"""The starts shared between solvers: CSF2's automatic K and the shared CSF2 start."""

import numpy as np

from nrsfm import solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d


def test_auto_k_leaves_the_factorisation_short_of_w():
    """3K = 2F makes the rank-3K factorisation all of W, which leaves the cameras free: three frames of a K = 2
    sequence gave CSF2 e3D 17.0 with K = 2."""
    from nrsfm.solvers.starts import auto_k

    assert auto_k(lowrank_sequence(3, 15, 2, seed=1).measurement_matrix()) == 1
    assert auto_k(lowrank_sequence(4, 15, 2, seed=1).measurement_matrix()) == 2
    assert auto_k(lowrank_sequence(40, 9, 2, seed=1).measurement_matrix()) == 2  # 3K < P as well


def test_auto_k_with_missing_points_matches_complete_tracks():
    """Nearly rigid tracks (the face, rank 7) with 20% missing get the complete tracks' K, not the cap (8)."""
    from nrsfm.datasets.synthetic import face_sequences
    from nrsfm.solvers.starts import auto_k

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


def test_auto_k_finds_the_rank_of_noisy_low_rank_tracks():
    """Noisy tracks have full numerical rank; the automatic K used to take its cap (8) there, which on a smooth
    camera gave CSF2 e3D .61. The noise threshold finds the rank; a spectrum without a gap keeps the cap."""
    from nrsfm.datasets.synthetic import face_sequences
    from nrsfm.lowrank import noise_rank
    from nrsfm.solvers.starts import auto_k

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


def test_consensus_computes_the_shared_csf2_start_once(monkeypatch):
    import nrsfm.solvers.csf2 as csf2
    import nrsfm.solvers.starts as starts

    seq = lowrank_sequence(40, 12, 2, seed=3, noise=0.01, missing=0.2)
    kw = dict(camera_rounds=3, round_iter=5, round_iter_alt=0)
    alone = starts.csf2_start(seq, 0, **kw)
    k = solve(seq, "csf2", k_rule="rank", **kw).info["K"]
    np.testing.assert_array_equal(starts.csf2_start(seq, k, **kw), alone)  # the automatic K's start is K's
    calls = []
    real = csf2.solve_csf2.__wrapped__

    def counted(s, params):
        calls.append(params)
        return real(s, params)

    monkeypatch.setattr(csf2.solve_csf2, "__wrapped__", counted)
    with starts.shared_starts():
        first = starts.csf2_start(seq, 0, **kw)
        first[:] = 0.0  # a copy: the cached start is untouched
        np.testing.assert_array_equal(starts.csf2_start(seq, k, **kw), alone)
        np.testing.assert_array_equal(starts.csf2_start(seq, 0, **kw), alone)
        assert len(calls) == 1
        starts.csf2_start(seq, 0, camera_rounds=4, round_iter=5, round_iter_alt=0)  # other settings: solved again
        assert len(calls) == 2
    starts.csf2_start(seq, 0, **kw)  # the cache ended with the block
    assert len(calls) == 3
    calls.clear()
    ranks = []
    real_rank = starts.noise_visible_rank
    monkeypatch.setattr(starts, "noise_visible_rank", lambda *a, **kw: ranks.append(real_rank(*a, **kw)) or ranks[-1])
    solve(seq, "consensus")  # EM-PND's start with missing points is PR's occlusion-aware start
    assert sum(c.camera_rounds == 50 and c.round_iter == 5 for c in calls) == 1
    assert len(ranks) == 1  # PR's automatic K and CSF2's (in pixels / a power of two) share the noise rank
    solve(seq, "csf2", k_rule="rank", **kw)
    assert len(ranks) == 2  # outside the consensus: computed again


def test_exact_rank_of_noise_free_tracks_and_none_for_noisy_ones():
    from nrsfm.solvers.starts import exact_rank

    seq = lowrank_sequence(60, 20, 3, seed=4)
    w = seq.measurement_matrix()
    assert exact_rank(w) == 9
    missing = lowrank_sequence(60, 20, 3, seed=4, missing=0.2)
    assert exact_rank(missing.measurement_matrix(), np.repeat(missing.weights > 0, 2, axis=0)) == 9
    noisy = lowrank_sequence(60, 20, 3, seed=4, noise=0.01)
    assert exact_rank(noisy.measurement_matrix()) == 0
