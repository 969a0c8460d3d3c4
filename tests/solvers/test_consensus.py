"""The consensus of several solvers."""

import numpy as np
import pytest

from nrsfm import SolverError, ValidationError, solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d


# ------------------------------------------------------------------ consensus
def test_consensus_recovers_a_noise_free_low_rank_sequence_and_says_what_it_ran():
    seq = lowrank_sequence(60, 15, 2, seed=1)
    rec = solve(seq, "consensus")
    assert e3d(rec.points_3d, seq.points_3d) < 1e-3
    assert rec.info["methods"] == ["empnd", "pr"] and rec.info["weights"] == [0.85, 0.15]
    assert rec.iterations == sum(rec.info["component_iterations"]) and np.isfinite(rec.rotations).all()
    missing = lowrank_sequence(60, 15, 2, seed=1, missing=0.2)
    assert e3d(solve(missing, "consensus").points_3d, missing.points_3d) < 0.02


def test_consensus_reuses_the_components_this_process_has_and_keeps_those_it_solves(monkeypatch):
    import dataclasses

    from nrsfm.solvers import registry, starts

    seq = lowrank_sequence(40, 12, 2, seed=3, noise=0.01, missing=0.1)
    solved = solve(seq, "consensus")
    assert solved.info["reused"] == [] and starts.remembered_solution(seq, "pr") is not None
    handed = {name: solve(seq, name) for name in ("empnd", "pr")}  # what another process would hand over

    def refuse(seq, params=None):
        raise AssertionError("a component was solved again")

    monkeypatch.setattr(starts, "_SOLUTIONS", type(starts._SOLUTIONS)())
    for name, rec in handed.items():
        starts.remember_solution(seq, name, rec)
        monkeypatch.setitem(registry._REGISTRY, name, dataclasses.replace(registry.get_solver(name), solve=refuse))
    reused = solve(seq.replace(name="elsewhere"), "consensus")
    assert reused.info["reused"] == ["empnd", "pr"]
    assert reused.info["component_seconds"] == [handed["empnd"].runtime_s, handed["pr"].runtime_s]
    np.testing.assert_allclose(reused.points_3d, solved.points_3d)


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
    with pytest.raises(SolverError, match="^consensus: rank3: expected complete tracks"):
        solve(lowrank_sequence(30, 10, 2, seed=0, missing=0.1), "consensus", methods="empnd,rank3", weights="1,1")
