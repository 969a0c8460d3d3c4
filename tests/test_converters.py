import numpy as np
import pytest

from nrsfm import ValidationError
from nrsfm.converters import from_akhter, from_measurement_matrix, from_pnd, to_pnd
from nrsfm.datasets.synthetic import lowrank_sequence


def _akhter_arrays(seq, rng, translate=True):
    """Build an Akhter-layout (W, S, Rs) from a synthetic sequence with a world frame."""
    world_rot = seq.camera_rotations  # X_cam = R X_obj
    s_obj = np.einsum("fpi,fij->fpj", seq.points_3d, world_rot)  # (F, P, 3) object frame
    if translate:
        s_obj = s_obj + rng.standard_normal((seq.n_frames, 1, 3))
    rs = world_rot[:, :2]  # (F, 2, 3)
    w = np.einsum("fij,fpj->fpi", rs, s_obj)  # (F, P, 2)
    to_rows = lambda a: a.transpose(0, 2, 1).reshape(-1, a.shape[1])  # noqa: E731
    return to_rows(w), to_rows(s_obj), rs.reshape(-1, 3), s_obj


@pytest.mark.parametrize("with_rs", [True, False])
def test_akhter_ground_truth_projects_to_2d_and_keeps_rotations(rng, with_rs):
    seq = lowrank_sequence(30, 12, 3, seed=5)
    w, s, rs, s_obj = _akhter_arrays(seq, rng)
    out = from_akhter(w, s, rs if with_rs else None, edges=np.array([[1, 2], [2, 3]]), scale=2.0)
    np.testing.assert_allclose(out.points_3d[..., :2], out.points_2d, atol=1e-9)
    np.testing.assert_allclose(out.camera_rotations, seq.camera_rotations, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(out.camera_rotations), 1.0, atol=1e-12)
    # the camera-frame ground truth is the rotated world shape (up to translation)
    rot_world = np.einsum("fij,fpj->fpi", seq.camera_rotations, s_obj)
    np.testing.assert_allclose(out.points_3d - out.points_3d.mean(1, keepdims=True),
                               rot_world - rot_world.mean(1, keepdims=True), atol=1e-9)
    np.testing.assert_array_equal(out.edges, [[0, 1], [1, 2]])
    assert out.meta["scale"] == "2.0"


def test_akhter_rejects_bad_shapes(rng):
    with pytest.raises(ValidationError, match=r"W: expected \(2F, P\)"):
        from_akhter(np.zeros((5, 4)))
    with pytest.raises(ValidationError, match=r"S: expected \(3F, P\) = \(6, 4\)"):
        from_akhter(np.zeros((4, 4)), np.zeros((9, 4)))


def test_pnd_roundtrip(rng):
    x = rng.standard_normal((3, 7, 11))
    seq = from_pnd(x)
    assert (seq.n_frames, seq.n_points) == (11, 7)
    np.testing.assert_array_equal(seq.points_2d, x[:2].transpose(2, 1, 0))
    np.testing.assert_array_equal(to_pnd(seq), x)
    with pytest.raises(ValidationError, match=r"X: expected \(3, P, F\)"):
        from_pnd(rng.standard_normal((11, 7, 3)))


def test_measurement_matrix_roundtrip(rng):
    seq = lowrank_sequence(6, 5, 1)
    np.testing.assert_array_equal(from_measurement_matrix(seq.measurement_matrix()).points_2d, seq.points_2d)
