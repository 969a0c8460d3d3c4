"""Mirror images of skeletons: the left / right pairing, the mirrored sequence and test-time mirroring."""

import numpy as np
import pytest
import torch

from nrsfm.datasets.h36m import JOINT_NAMES
from nrsfm.datasets.synthetic import human_sequences
from prn.data import build_training_set, mirror_permutation, mirror_perms, mirror_points, mirror_sequence
from prn.model import PRNFCN
from prn.train import predict, predict_mirrored


def test_mirror_permutation_pairs_left_and_right_joints_by_name():
    perm = mirror_permutation(JOINT_NAMES)
    names = list(JOINT_NAMES)
    assert names[perm[names.index("LShoulder")]] == "RShoulder" and names[perm[names.index("RFoot")]] == "LFoot"
    assert perm[names.index("Hip")] == names.index("Hip") and (perm[perm] == np.arange(17)).all()
    assert list(mirror_permutation(["leftKnee", "rightKnee", "pelvis"])) == [1, 0, 2]
    assert list(mirror_permutation(["l_ankle", "neck", "r_ankle"])) == [2, 1, 0]
    # no names, no pair, a side without its partner, or names that only begin with L / R
    for names in (None, (), ("Hip", "Spine"), ("LHip", "Hip"), ("Lips", "Rest")):
        assert mirror_permutation(names) is None


def test_mirrored_sequence_is_the_mirror_image_of_the_scene_and_a_take_of_its_own():
    seq = human_sequences(("S1",), ("walking",), n_frames=8)[0]
    perm = mirror_permutation(JOINT_NAMES)
    m = mirror_sequence(seq, perm)
    np.testing.assert_allclose(m.points_2d[:, 1, 0], -seq.points_2d[:, 4, 0])  # RHip takes LHip's x, negated
    np.testing.assert_allclose(m.points_2d[..., 1], seq.points_2d[:, perm, 1])
    np.testing.assert_allclose(m.points_3d[..., :2], m.points_2d)  # still an orthographic view of its 3D
    np.testing.assert_allclose(mirror_points(m.points_3d, perm), seq.points_3d)  # its own inverse
    assert m.meta["subject"] != seq.meta.get("subject", seq.name) and m.name != seq.name


def test_mirrored_prediction_is_mirror_equivariant_and_one_frame_at_a_time():
    torch.manual_seed(0)
    net = PRNFCN(17, 17, width=64).eval()
    seq = human_sequences(("S1",), ("walking",), n_frames=6)[0]
    data = build_training_set([seq])
    x, w = data.prepare_inputs(seq)
    p_in, p_out = mirror_perms(JOINT_NAMES, data.input_points)
    y = predict_mirrored(net, x, w, p_in, p_out)
    np.testing.assert_allclose(predict_mirrored(net, mirror_points(x, p_in), w[:, p_in], p_in, p_out),
                               mirror_points(y, p_out), atol=1e-5)
    np.testing.assert_allclose(predict_mirrored(net, x[2:3], w[2:3], p_in, p_out), y[2:3], atol=1e-5)
    assert np.abs(y - predict(net, x, w)).max() > 1e-4  # the plain network is not mirror-symmetric


@pytest.mark.parametrize("inputs", [None, np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 10, 11, 12, 13, 14, 15, 16])])
def test_mirror_perms_follow_the_networks_input_points(inputs):
    """SH's network reads 16 of the 17 joints (no Neck/Nose): its input permutation indexes those 16."""
    p_in, p_out = mirror_perms(JOINT_NAMES, inputs)
    keep = np.arange(17) if inputs is None else inputs
    np.testing.assert_array_equal(keep[p_in], p_out[keep])
    assert mirror_perms(JOINT_NAMES, np.array([0, 1, 2, 3])) is None  # RHip's partner is no input
