"""Mixed pseudo-labels: the frame-by-frame mean of several solvers' label sets."""

import numpy as np
import pytest

from baselines.label_mix import mix_labels, mix_shapes, parse_label_solvers
from baselines.labels import LabelSet, label_error
from nrsfm.datasets.synthetic import human_sequences
from nrsfm.errors import ValidationError

MIRROR = np.array([1.0, 1.0, -1.0])


@pytest.fixture(scope="module")
def walk():
    return human_sequences(("S1",), ("walking",), projection="orthographic", n_frames=20, takes=1)[:2]


def test_two_sets_with_opposite_depth_errors_average_to_the_truth_whatever_their_handedness(walk):
    """Depth errors of opposite sign cancel; a set mirrored frame by frame is flipped back before the mean."""
    truth = [s.points_3d for s in walk]
    noise = [np.random.default_rng(i).normal(0, 40, t.shape) * np.array([0, 0, 1]) for i, t in enumerate(truth)]
    a = [t + n for t, n in zip(truth, noise)]
    flip = np.random.default_rng(3).random(truth[0].shape[0]) < 0.5
    b = [np.where(flip[:, None, None], (t - n) * MIRROR, t - n) for t, n in zip(truth, noise)]
    mixed = [mix_shapes([x, y], np.array([0.5, 0.5])) for x, y in zip(a, b)]
    for m, t in zip(mixed, truth):
        np.testing.assert_allclose(m, t - t.mean(axis=1, keepdims=True), atol=1e-9)
    assert label_error(mixed, walk) < 1e-6 < label_error(a, walk)


def test_a_set_without_a_label_leaves_the_entry_to_the_others_and_none_leaves_nan(walk):
    t = walk[0].points_3d
    a, b = t.copy(), t + np.array([0.0, 0.0, 10.0])
    a[0] = np.nan  # a failed cut in the first set
    a[1:, 9], b[1:, 9] = np.nan, np.nan  # a point no cut saw
    b[2] = np.nan
    m = mix_shapes([a, b], np.array([0.3, 0.7]))
    centred = t - t.mean(axis=1, keepdims=True)
    np.testing.assert_allclose(m[0], centred[0], atol=1e-9)  # b alone, centred
    assert np.isnan(m[1:, 9]).all() and np.isfinite(np.delete(m, 9, axis=1)).all()
    keep = np.arange(t.shape[1]) != 9
    np.testing.assert_allclose(m[2][keep], (t[2][keep] - t[2][keep].mean(axis=0)), atol=1e-9)  # a alone


def test_mix_labels_summary_names_both_solvers_and_scores_the_mixture(walk):
    truth = [s.points_3d for s in walk]
    base = {"cuts": 4, "frames": 40, "dataset": "walk", "gap": 5, "failed": 0}
    sets = [LabelSet([t + d for t in truth], {**base, "method": m, "params": p, "seconds": 2.0, "label_mpjpe": 1.0},
                     {"S1/walking/o0c0": "x"} if m == "pr" else {})
            for m, p, d in (("pr", {"max_iter": 200}, 0.0), ("empnd", {}, 1.0))]
    out = mix_labels(sets, truth=walk)
    s = out.summary
    assert s["method"] == "pr+empnd" and s["params"] == {"pr": {"max_iter": 200}, "empnd": {}}
    assert s["weights"] == [0.5, 0.5] and s["seconds"] == 4.0 and s["failed"] == 0  # a cut fails when all do
    assert s["label_mpjpe"] < 1.0 and s["labelled_frames"] == 40


def test_bad_mixtures_are_refused_with_the_expected_form():
    assert parse_label_solvers("pr+empnd") == ["pr", "empnd"] and parse_label_solvers("pr") == ["pr"]
    for text in ("pr+", "pr+pr", "+empnd"):
        with pytest.raises(ValidationError, match="joined by"):
            parse_label_solvers(text)
    with pytest.raises(ValidationError, match="non-negative weights"):
        mix_shapes([np.zeros((2, 3, 3))] * 2, np.array([1.0, -1.0]))
    with pytest.raises(ValidationError, match="one shape"):
        mix_shapes([np.zeros((2, 3, 3)), np.zeros((2, 4, 3))], np.array([1.0, 1.0]))
    with pytest.raises(ValidationError, match="two or more"):
        mix_labels([LabelSet([], {})])
