"""K chosen by agreement with a reconstruction that needs no K (CSF2's default rule)."""

import dataclasses

import numpy as np
import pytest

from nrsfm import Reconstruction, solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.errors import SolverError, ValidationError
from nrsfm.metrics import e3d
from nrsfm.solvers import kselect, starts
from nrsfm.solvers.kselect import agreement_k, depth_flips, k_candidates, steady_ks


def test_agreement_keeps_the_k_nearest_the_reference_and_skips_a_failed_k():
    rng = np.random.default_rng(0)
    reference = rng.standard_normal((20, 10, 3))
    noise = rng.standard_normal(reference.shape)

    def solve_k(k):
        if k == 4:
            raise SolverError("K = 4 does not fit")
        return Reconstruction(points_3d=reference + 0.1 * abs(k - 3) * noise, rotations=None, method="fake")

    rec, dist, _ = agreement_k(solve_k, range(1, 6), reference)
    assert np.allclose(rec.points_3d, reference) and dist[3] < 1e-12
    assert np.isnan(dist[4]) and dist[1] > dist[2] > dist[3] and dist[5] > dist[3]
    # a reflection in depth is the same reconstruction (orthographic depth has no sign)
    rec, dist, _ = agreement_k(solve_k, [3], reference * np.array([1.0, 1.0, -1.0]))
    assert dist[3] < 1e-12
    with pytest.raises(SolverError, match="no K"):
        agreement_k(lambda k: solve_k(4), [4], reference)


def test_agreement_keeps_the_largest_k_within_the_tolerance_of_the_nearest():
    rng = np.random.default_rng(1)
    reference = rng.standard_normal((30, 10, 3))
    noise = rng.standard_normal(reference.shape)
    scale = {1: 0.1, 2: 0.102, 3: 0.2, 4: 0.15}  # K = 2 is within 5% of the nearest (K = 1); K = 3 and 4 are not

    def solve_k(k):
        return Reconstruction(points_3d=reference + scale[k] * noise, rotations=None, method="fake")

    rec, dist, flips = agreement_k(solve_k, [1, 2, 3, 4], reference)
    assert sorted(flips) == [1, 2, 3, 4]  # random shapes, not a motion: the flip guard passes over no K
    assert dist[1] < dist[2] <= (1 + kselect.TOLERANCE) * dist[1] < dist[4] < dist[3]
    assert np.allclose(rec.points_3d, solve_k(2).points_3d)


def _walker(n_frames: int = 60) -> np.ndarray:
    """`(F, 8, 3)` a rigid body with depth turning steadily about the vertical axis."""
    rng = np.random.default_rng(3)
    body = rng.standard_normal((8, 3))
    t = np.linspace(0.0, 1.0, n_frames)
    c, s = np.cos(t), np.sin(t)
    rot = np.stack([np.stack([c, 0 * t, s], -1), np.tile([0.0, 1.0, 0.0], (n_frames, 1)),
                    np.stack([-s, 0 * t, c], -1)], 1)  # (F, 3, 3)
    return np.einsum("fij,pj->fpi", rot, body)


def test_depth_flips_counts_the_frames_whose_depth_sign_reverses():
    x = _walker()
    assert depth_flips(x) == 0.0 and depth_flips(x[:1]) == 0.0
    y = x.copy()
    y[30:40, :, 2] *= -1  # a run of mirrored frames: two reversals, in and out
    assert depth_flips(y) == pytest.approx(2 / 59)
    y[::2, :, 2] *= -1  # every other frame mirrored
    assert depth_flips(y) > 0.9
    assert depth_flips(x * np.array([1.0, 1.0, -1.0])) == 0.0  # the whole sequence mirrored is still steady


def test_steady_ks_pass_over_a_k_that_flips_more_than_the_steadiest():
    assert steady_ks({2: 0.007, 3: 0.087, 4: 0.0, 5: 0.0}) == [2, 4, 5]  # least 0: up to FLIP_MARGIN
    assert steady_ks({2: 0.064, 3: 0.030, 4: 0.007, 5: 0.020}) == [4]  # least .007: up to .017
    assert steady_ks({1: 0.094, 2: 0.090, 3: 0.084}) == [1, 2, 3]  # all flip alike: up to twice the least
    assert steady_ks({1: 0.5, 2: 0.45, 3: 0.55}) == [1, 2, 3]  # frames out of order: no K is passed over


def test_agreement_passes_over_a_k_that_flips_even_where_it_is_nearest_the_reference():
    truth = _walker()
    rng = np.random.default_rng(4)
    mirror = np.array([1.0, 1.0, -1.0])
    flipping = truth.copy()
    flipping[::7] *= mirror  # a reference that reverses depth in one frame of seven
    noise = rng.standard_normal(truth.shape)

    def solve_k(k):
        shapes = flipping if k == 3 else truth + 0.02 * k * noise  # K = 3 shares the reference's fault
        return Reconstruction(points_3d=shapes, rotations=None, method="fake")

    rec, dist, flips = agreement_k(solve_k, [2, 3, 4], flipping)
    assert dist[3] < 1e-12 < dist[2] and flips[3] > 0.2 and flips[2] == flips[4] == 0.0
    assert np.allclose(rec.points_3d, solve_k(2).points_3d) or np.allclose(rec.points_3d, solve_k(4).points_3d)


def test_k_candidates_keep_3k_below_the_frames_and_points():
    assert list(k_candidates(300, 17)) == [1, 2, 3, 4, 5]
    assert list(k_candidates(300, 41)) == list(range(1, 13))  # capped at 12
    assert list(k_candidates(300, 68)) == list(range(1, 13))
    assert list(k_candidates(2, 41)) == [1]  # 3K < 2F
    assert list(k_candidates(40, 4)) == [1]


def test_csf2_default_k_is_the_agreement_rule_and_finds_the_k_of_low_rank_tracks():
    seq = lowrank_sequence(60, 12, 2, seed=1, cameras="random", noise=0.005)
    rec = solve(seq, "csf2")
    dist = rec.info["agreement"]
    assert rec.info["k_rule"] == "agreement" and sorted(dist) == [1, 2, 3]
    steady = steady_ks(rec.info["depth_flips"])
    least = min(dist[k] for k in steady)
    assert rec.info["K"] == max(k for k in steady if dist[k] <= (1 + kselect.TOLERANCE) * least)
    assert e3d(rec.points_3d, seq.points_3d) <= 1.1 * min(e3d(solve(seq, "csf2", K=k).points_3d, seq.points_3d)
                                                          for k in (1, 2, 3))
    assert "agreement" not in solve(seq, "csf2", k_rule="rank").info
    with pytest.raises(ValidationError, match="k_rule"):
        solve(seq, "csf2", k_rule="best")


def test_csf2_and_spm_on_the_same_tracks_compute_the_reference_once(monkeypatch):
    from nrsfm.solvers.registry import get_solver

    spec = get_solver("empnd")
    calls = []
    real = spec.solve.__wrapped__

    def counted(seq, params):
        calls.append(seq.name)
        return real(seq, params)

    monkeypatch.setattr(spec.solve, "__wrapped__", counted)
    seq = lowrank_sequence(40, 12, 2, seed=4, noise=0.01)
    solve(seq, "csf2"), solve(seq, "spm"), solve(seq.replace(name="renamed"), "csf2")
    assert len(calls) == 1  # the same tracks under another name are the same input
    solve(lowrank_sequence(40, 12, 2, seed=5, noise=0.01), "csf2")
    assert len(calls) == 2


def test_a_reference_handed_over_is_used_instead_of_solving_it(monkeypatch):
    from nrsfm.solvers.registry import get_solver

    seq = lowrank_sequence(40, 12, 2, seed=7, noise=0.01)
    solved = solve(seq, "csf2")
    reference = solve(seq, kselect.REFERENCE_SOLVER)  # what another process would hand over

    def refuse(seq, params):
        raise AssertionError("the reference was solved again")

    monkeypatch.setattr(get_solver("empnd").solve, "__wrapped__", refuse)
    monkeypatch.setattr(starts, "_SOLUTIONS", type(starts._SOLUTIONS)())
    starts.remember_solution(seq, kselect.REFERENCE_SOLVER, reference)
    handed = solve(seq.replace(name="elsewhere"), "csf2")
    assert handed.info["K"] == solved.info["K"] and handed.info["agreement"] == pytest.approx(solved.info["agreement"])
    np.testing.assert_allclose(handed.points_3d, solved.points_3d)
    cut = dataclasses.replace(reference, points_3d=reference.points_3d[:, :11])
    with pytest.raises(ValueError, match=r"expected a Reconstruction with shapes of shape \(40, 12, 3\) .*, "
                                         r"got \(40, 11"):
        starts.remember_solution(seq, "empnd", cut)


def test_the_k_solves_in_worker_processes_give_the_sequential_result():
    from joblib import parallel_config

    seq = lowrank_sequence(60, 12, 2, seed=1, cameras="random", noise=0.005)
    one = solve(seq, "csf2")
    with parallel_config(backend="loky", n_jobs=2, inner_max_num_threads=1):
        two = solve(seq, "csf2")
    assert two.info["K"] == one.info["K"] and two.info["agreement"] == pytest.approx(one.info["agreement"])
    np.testing.assert_allclose(two.points_3d, one.points_3d)


def test_where_the_reference_fails_the_fallback_rule_chooses_k_and_says_why(monkeypatch):
    from nrsfm.solvers.registry import get_solver

    def refuse(seq, params):
        raise SolverError("empnd: degenerate tracks")

    monkeypatch.setattr(get_solver("empnd").solve, "__wrapped__", refuse)
    seq = lowrank_sequence(40, 12, 2, seed=6, noise=0.01)
    rec = solve(seq, "csf2")
    assert rec.info["k_rule"].startswith("rank (the agreement rule's reference failed: empnd: degenerate")
    assert "agreement" not in rec.info and rec.info["K"] == solve(seq, "csf2", k_rule="rank").info["K"]


def test_fill_missing_keeps_visible_points_and_projects_the_shapes_at_the_hidden_ones():
    from nrsfm.datasets.synthetic import drop_entries

    seq = lowrank_sequence(30, 12, 2, seed=2, noise=0.01)
    assert kselect.fill_missing(seq, seq.points_3d) is seq  # complete tracks: nothing to fill
    holed = drop_entries(seq, 0.3)
    vis = holed.weights > 0
    shapes = seq.points_3d + 0.05 * np.random.default_rng(3).standard_normal(seq.points_3d.shape)
    filled = kselect.fill_missing(holed.replace(points_2d=np.where(vis[..., None], holed.points_2d, np.nan)), shapes)
    assert filled.is_complete and np.array_equal(filled.points_2d[vis], seq.points_2d[vis])
    shift = np.array([(seq.points_2d[f] - shapes[f, :, :2])[vis[f]].mean(axis=0) for f in range(30)])  # (F, 2)
    expected = shapes[..., :2] + shift[:, None, :]
    np.testing.assert_allclose(filled.points_2d[~vis], expected[~vis])


def test_with_missing_points_every_k_is_solved_on_the_tracks_the_reference_completes():
    from nrsfm.datasets.synthetic import drop_entries

    seq = drop_entries(lowrank_sequence(40, 15, 2, seed=8, noise=0.01), 0.2)
    rec = solve(seq, "csf2")
    assert rec.info["completion"] == "reference" and rec.info["k_rule"] == "agreement"
    reference = solve(seq, kselect.REFERENCE_SOLVER)
    filled = kselect.fill_missing(seq, reference.points_3d)
    same = solve(filled, "csf2", K=rec.info["K"])  # the kept K, solved on the completed tracks
    np.testing.assert_allclose(rec.points_3d, same.points_3d)
    assert same.info["completion"] == "none"
    assert rec.info["agreement"][rec.info["K"]] == pytest.approx(e3d(same.points_3d, reference.points_3d))
    assert solve(seq, "csf2", K=2).info["completion"] in ("exact", "imputed")  # a fixed K completes on its own


@pytest.mark.parametrize("method", ["csf2", "spm"])
def test_fill_chooses_how_missing_points_are_completed_at_any_k(method):
    from nrsfm.datasets.synthetic import drop_entries

    seq = drop_entries(lowrank_sequence(40, 15, 2, seed=9, noise=0.01), 0.2)
    filled = kselect.fill_from_reference(seq)
    by_reference = solve(seq, method, K=2, fill="reference")
    assert by_reference.info["completion"] == "reference"
    np.testing.assert_allclose(by_reference.points_3d, solve(filled, method, K=2).points_3d)
    assert solve(seq, method, K=2).info["completion"] in ("exact", "imputed")  # "auto" with a fixed K
    own = solve(seq, method, fill="lowrank")  # the automatic K with each K completing the tracks itself
    assert own.info["completion"] in ("exact", "imputed") and own.info["k_rule"] == "agreement"
    assert solve(seq.replace(visibility=None), method, K=2, fill="reference").info["completion"] == "none"
    with pytest.raises(ValidationError, match="fill: expected one of"):
        solve(seq, method, fill="mean")
