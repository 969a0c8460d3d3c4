"""The supervised 3D network of the "+NN" and "GT 3D" rows."""

import numpy as np
import pytest

from baselines.supervised import Supervised3D, normalised_targets, train_supervised
from nrsfm.datasets.synthetic import human_sequences
from nrsfm.metrics import mpjpe_prn
from prn.data import denormalize
from prn.train import TrainConfig, predict


def test_targets_skip_unlabelled_frames_and_refuse_an_empty_set():
    shapes = [np.random.default_rng(0).standard_normal((5, 4, 3))]
    shapes[0][2] = np.nan
    t = normalised_targets(shapes)
    assert np.isnan(t[2]).all() and np.isfinite(np.delete(t, 2, axis=0)).all()
    np.testing.assert_allclose(np.linalg.norm(t[0, :, :2]), 1.0)
    obj = Supervised3D(t, batch=8)
    assert set(obj.sample(np.random.default_rng(0))) <= {0, 1, 3, 4}
    with pytest.raises(ValueError, match="no training frame"):
        Supervised3D(np.full((3, 4, 3), np.nan))


def test_ground_truth_supervision_learns_depth_that_zero_depth_does_not(tmp_path):
    seqs = human_sequences(("S1", "S5"), ("walking",), projection="orthographic", n_frames=40, takes=1)
    test = human_sequences(("S9",), ("walking",), projection="orthographic", n_frames=40, takes=1)
    config = TrainConfig(iterations=300, lr_step=100, width=128, checkpoint_every=100, device="cpu")
    result, data = train_supervised(seqs, [s.points_3d for s in seqs], config, tmp_path, progress=False)
    errors, flat = [], []
    for seq in test:
        x, w = data.prepare_inputs(seq)
        pred = denormalize(predict(result.model, x, w), seq.points_3d)
        errors.append(mpjpe_prn(pred, seq.points_3d))
        flat.append(mpjpe_prn(np.concatenate([pred[..., :2], 0 * pred[..., 2:]], axis=2), seq.points_3d))
    assert np.mean(errors) < 0.8 * np.mean(flat)
