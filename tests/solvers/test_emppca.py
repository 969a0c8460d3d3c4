"""EM-PPCA (Torresani et al.)."""

from nrsfm import solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d


def test_emppca_recovers_a_noise_free_low_rank_sequence_and_handles_missing_points():
    seq = lowrank_sequence(200, 30, 3, seed=0)
    assert e3d(solve(seq, "emppca", K=3).points_3d, seq.points_3d) < 1e-3
    seq = lowrank_sequence(120, 25, 2, seed=2, missing=0.2)
    assert e3d(solve(seq, "emppca", K=2).points_3d, seq.points_3d) < 0.02
