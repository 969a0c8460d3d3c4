"""The rigid factorisation."""

import numpy as np
import pytest

from nrsfm import SolverError, solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d
from nrsfm.sequence import Sequence


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
