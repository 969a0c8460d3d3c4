import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from nrsfm import ValidationError
from nrsfm.metrics import (camera_moves, classic_metrics, e3d, e3d_per_frame, mpjpe_best_flip, mpjpe_prn,
                           mpjpe_prn_per_joint, normalized_error, pa_mpjpe, rotation_error, rotation_error_per_frame,
                           stress)

MIRROR = np.array([1.0, 1.0, -1.0])


# ------------------------------------------------------------------ hand-built cases with known values
def test_e3d_known_value_scale_and_rotation():
    gt = np.array([[[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]], dtype=float)
    # rows x and y have population std sqrt(1/2), row z has 0: s = 2 sqrt(1/2) / 3
    # pred = 2 gt: the global fit is projected to a rotation (I), each point is off by 1
    assert e3d(2 * gt, gt) == pytest.approx(1 / (2 * np.sqrt(0.5) / 3))
    rot = Rotation.from_euler("xyz", [0.3, -1.0, 2.0]).as_matrix()
    assert e3d(gt @ rot.T, gt) == pytest.approx(0, abs=1e-12)


def test_e3d_object_frame_removes_per_frame_cameras(rng):
    shapes = rng.standard_normal((6, 9, 3))
    rots_gt = Rotation.random(6, random_state=1).as_matrix()
    rots_pred = Rotation.random(6, random_state=2).as_matrix()
    gt = np.einsum("fij,fpj->fpi", rots_gt, shapes)
    pred = np.einsum("fij,fpj->fpi", rots_pred, shapes)
    assert e3d(pred, gt) > 0.1  # camera frame: the rotations differ
    assert e3d(pred, gt, frame="object", pred_rotations=rots_pred, gt_rotations=rots_gt) == pytest.approx(0, abs=1e-9)
    with pytest.raises(ValidationError, match="pred_rotations and gt_rotations"):
        e3d(pred, gt, frame="object")


def test_normalized_error_known_value():
    gt = np.array([[[1, 2, 0], [-1, 0, 0], [0, -2, 0]]], dtype=float)
    assert normalized_error(1.1 * gt, gt) == pytest.approx(0.1)
    assert normalized_error(gt + 5.0, gt) == pytest.approx(0.0)  # translation is removed


def test_mpjpe_known_values_and_z_sign():
    gt = np.array([[[1, 0, 1], [-1, 0, -1]]], dtype=float)
    assert mpjpe_prn(gt * MIRROR, gt) == pytest.approx(0.0)
    assert mpjpe_prn(gt * MIRROR, gt, z_sign="none") == pytest.approx(2.0)
    pred = gt + np.array([[[0, 3, 0], [0, -3, 0]]])
    assert mpjpe_prn(pred, gt) == pytest.approx(3.0)
    per_joint = mpjpe_prn_per_joint(pred, gt)
    assert per_joint.shape == gt.shape[:2] and per_joint.mean() == pytest.approx(3.0)


def test_pa_mpjpe_and_reflection(rng):
    gt = rng.standard_normal((4, 10, 3))
    rot = Rotation.random(random_state=3).as_matrix()
    assert pa_mpjpe(2.5 * gt @ rot.T + 7, gt) == pytest.approx(0, abs=1e-9)
    assert pa_mpjpe(gt * MIRROR, gt) > 0.1
    assert pa_mpjpe(gt * MIRROR, gt, allow_reflection=True) == pytest.approx(0, abs=1e-9)


def test_best_flip_and_stress_known_values():
    gt = np.array([[[0, 0, 0], [2, 0, 0]]], dtype=float)
    pred = np.array([[[0, 0, 0], [3, 0, 0]]], dtype=float)
    assert stress(pred, gt) == pytest.approx(1.0)
    assert mpjpe_best_flip(pred, gt, root=0) == pytest.approx(0.5)
    gt3 = np.array([[[0, 0, 0], [1, 0, 2]]], dtype=float)
    assert mpjpe_best_flip(gt3 * MIRROR, gt3) == pytest.approx(0.0)
    assert stress(gt3 * MIRROR, gt3) == pytest.approx(0.0)


def test_rotation_error_known_values():
    gt = Rotation.random(5, random_state=3).as_matrix()
    frame = Rotation.random(random_state=4).as_matrix()
    mirror = np.diag([1.0, 1.0, -1.0])
    # a global change of object frame, proper or mirrored, costs nothing
    assert rotation_error(gt @ frame, gt) == pytest.approx(0, abs=1e-12)
    assert rotation_error(gt @ mirror, gt) == pytest.approx(0, abs=1e-12)
    # one frame turned by 180 degrees about the optical axis: both rows negated, |2 R_f[:2]| = 2 sqrt(2)
    turned = gt.copy()
    turned[2] = np.diag([-1.0, -1.0, 1.0]) @ gt[2]
    per_frame = rotation_error_per_frame(turned, gt)
    assert per_frame[2] > 1.0 and per_frame.mean() == pytest.approx(rotation_error(turned, gt))
    # with one frame in five flipped the best global fit is still close to the identity
    assert np.delete(per_frame, 2).max() < 1.0
    # each frame's error is the spectral norm of its (2, 3) difference (MATLAB's norm(), as in Akhter et al.'s
    # compareRotations), not the Frobenius norm: a turn by t about the optical axis costs 2 sin(t / 2), not
    # 2 sqrt(2) sin(t / 2); many exact frames keep the global fit at the identity
    many = Rotation.random(400, random_state=5).as_matrix()
    off = many.copy()
    off[0] = Rotation.from_rotvec([0, 0, np.pi]).as_matrix() @ many[0]
    off[1] = Rotation.from_rotvec([0, 0, 0.1]).as_matrix() @ many[1]
    per_frame = rotation_error_per_frame(off, many)
    assert per_frame[0] == pytest.approx(2.0, abs=0.02) and per_frame[1] == pytest.approx(2 * np.sin(0.05), rel=0.05)
    with pytest.raises(ValidationError, match=r"gt_rotations: expected \(F, 3, 3\) with F = 5"):
        rotation_error(gt, gt[:4])
    # a static ground-truth camera: no object frame or camera error in the classic metrics
    shapes = np.random.default_rng(0).standard_normal((5, 6, 3))
    static = np.broadcast_to(frame, (5, 3, 3))
    assert camera_moves(gt) and not camera_moves(static)
    assert "rotation_error" in classic_metrics(shapes, shapes, pred_rotations=gt, gt_rotations=gt)
    assert "e3d_object" not in classic_metrics(shapes, shapes, pred_rotations=gt, gt_rotations=static)


def test_shape_mismatch_is_a_clear_error(rng):
    with pytest.raises(ValidationError, match=r"pred: expected the ground truth's shape \(2, 3, 3\)"):
        e3d(rng.standard_normal((2, 4, 3)), rng.standard_normal((2, 3, 3)))


# ------------------------------------------------------------------ properties
_dims = st.tuples(st.integers(1, 5), st.integers(3, 8), st.just(3))
_elements = st.floats(-10, 10, allow_nan=False, width=64)
shapes = arrays(np.float64, _dims, elements=_elements)
pairs = _dims.flatmap(lambda d: st.tuples(arrays(np.float64, d, elements=_elements),
                                          arrays(np.float64, d, elements=_elements)))
rotations = st.tuples(*[st.floats(-np.pi, np.pi)] * 3).map(lambda a: Rotation.from_euler("xyz", a).as_matrix())


def _non_degenerate(x):
    """Not (nearly) a point or a line: the global 3x3 fit of e3D is ill-conditioned for collinear shapes
    (hypothesis found ``[[1e-10, 0, 0], [0, 1, 0], [0, 0, 0]]``: e3D 4.6e-7 against itself)."""
    c = x - x.mean(axis=1, keepdims=True)
    sv = np.linalg.svd(c.reshape(-1, 3), compute_uv=False)  # spread of all points over the sequence
    return (np.linalg.norm(c) > 1e-2 and np.linalg.norm(c.reshape(-1, c.shape[1] * 3), axis=1).min() > 1e-3
            and sv[1] > 1e-3 * sv[0])


@given(shapes)
def test_zero_for_ground_truth_and_its_mirror(gt):
    assume(_non_degenerate(gt))
    assert e3d(gt, gt) == pytest.approx(0, abs=1e-7)
    assert e3d(gt * MIRROR, gt) == pytest.approx(0, abs=1e-7)
    assert normalized_error(gt, gt) == pytest.approx(0, abs=1e-9)
    assert normalized_error(gt * MIRROR, gt) == pytest.approx(0, abs=1e-9)
    assert mpjpe_prn(gt * MIRROR, gt) == pytest.approx(0, abs=1e-9)


@given(pairs, rotations)
def test_e3d_invariant_to_a_global_rotation_of_the_prediction(pair, rot):
    gt, noise = pair
    assume(_non_degenerate(gt))
    pred = gt + 0.3 * noise
    c = (pred - pred.mean(axis=1, keepdims=True)).reshape(-1, 3)
    sv = np.linalg.svd(c, compute_uv=False)
    assume(sv[-1] > 1e-2 * sv[0])  # the global 3x3 fit is unique only for full-rank (non-planar) shapes
    a = e3d_per_frame(pred, gt)
    b = e3d_per_frame(pred @ rot.T, gt)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-8)


@given(pairs, rotations)
def test_per_frame_metrics_invariant_to_a_common_rotation_about_the_optical_axis(pair, rot):
    """The camera-frame protocols (normalised error, MPJPE) keep the optical axis: a rotation
    about z applied to both prediction and ground truth changes nothing."""
    gt, noise = pair
    assume(_non_degenerate(gt))
    rz = Rotation.from_euler("z", Rotation.from_matrix(rot).as_euler("xyz")[0]).as_matrix()
    pred = gt + 0.3 * noise
    assert normalized_error(pred @ rz.T, gt @ rz.T) == pytest.approx(normalized_error(pred, gt), rel=1e-7, abs=1e-9)
    assert mpjpe_prn(pred @ rz.T, gt @ rz.T) == pytest.approx(mpjpe_prn(pred, gt), rel=1e-7, abs=1e-9)
    assert stress(pred @ rot.T, gt) == pytest.approx(stress(pred, gt), rel=1e-7, abs=1e-9)


def test_normalized_error_is_not_rotation_invariant(rng):
    """Camera-frame protocol: a wrong viewpoint is an error (guards against silent alignment)."""
    gt = rng.standard_normal((3, 10, 3))
    rot = Rotation.from_euler("y", 0.5).as_matrix()
    assert normalized_error(gt @ rot.T, gt) > 0.1
