"""EM-PPCA (Torresani et al.)."""

import numpy as np
from scipy.spatial.transform import Rotation

from nrsfm import solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d
from nrsfm.sequence import Sequence
from nrsfm.solvers.emppca import DEFAULT_K


def test_emppca_recovers_a_noise_free_low_rank_sequence_and_handles_missing_points():
    seq = lowrank_sequence(200, 30, 3, seed=0)
    assert e3d(solve(seq, "emppca", K=3).points_3d, seq.points_3d) < 1e-3
    seq = lowrank_sequence(120, 25, 2, seed=2, missing=0.2)
    assert e3d(solve(seq, "emppca", K=2).points_3d, seq.points_3d) < 0.02


def test_automatic_k_of_noise_free_tracks_is_exact():
    """A mean and two modes (rank 9): K = 2, with and without missing points; noisy tracks keep DEFAULT_K, and so
    do 12 points of rank 9 (P - 3: a deficiency that points depending on others can make)."""
    for missing in (0.0, 0.2):
        seq = lowrank_sequence(120, 25, 3, seed=1, missing=missing)
        rec = solve(seq, "emppca")
        assert rec.info["K"] == 2
        assert e3d(rec.points_3d, seq.points_3d) < 1e-4
    assert solve(lowrank_sequence(120, 25, 3, seed=1, noise=0.01), "emppca").info["K"] == DEFAULT_K
    assert solve(lowrank_sequence(120, 12, 3, seed=1), "emppca").info["K"] == DEFAULT_K


def test_automatic_k_takes_one_more_mode_where_the_shapes_do_not_hold_their_mean():
    """Shapes that are free combinations of three bases (rank 9, no common mean): two modes cannot fit them
    exactly, three do (e3D .59 against .19 on these random cameras)."""
    rng = np.random.default_rng(3)
    shapes = np.einsum("fk,kpj->fpj", rng.standard_normal((150, 3)) + [1.0, 0.0, 0.0],
                       rng.standard_normal((3, 30, 3)))
    x = np.einsum("fij,fpj->fpi", Rotation.random(150, random_state=4).as_matrix(), shapes)
    x -= x.mean(axis=1, keepdims=True)
    seq = Sequence(points_2d=x[..., :2].copy(), points_3d=x)
    rec = solve(seq, "emppca")
    assert rec.info["K"] == 3
    assert e3d(rec.points_3d, x) < 0.3 < e3d(solve(seq, "emppca", K=2).points_3d, x)
