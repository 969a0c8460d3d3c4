"""Real CMU NRSfM files under $NRSFM_DATA/nrsfm (skipped when absent)."""

import numpy as np
import pytest

from nrsfm.cli import main
from nrsfm.datasets import list_cmu_sequences, load_cmu_mat
from nrsfm.errors import DataFormatError
from nrsfm.datasets import load_sequence

pytestmark = pytest.mark.realdata


def test_every_sequence_ground_truth_projects_onto_the_input(cmu_dir):
    files = list_cmu_sequences(cmu_dir)
    assert files, f"no .mat files in {cmu_dir}"
    for path in files:
        seq = load_cmu_mat(path)
        assert seq.has_ground_truth, path.name
        np.testing.assert_allclose(seq.points_3d[..., :2], seq.points_2d, atol=1e-9, err_msg=path.name)
        if seq.camera_rotations is not None:
            r = seq.camera_rotations
            np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-9)


def test_drink_convert_and_info(cmu_dir, tmp_path, capsys):
    out = tmp_path / "drink.npz"
    assert main(["convert", str(cmu_dir / "drink.mat"), str(out)]) == 0
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "frames: 1102" in text and "points: 41" in text and "ground truth: present" in text
    seq = load_sequence(out)
    np.testing.assert_allclose(seq.points_3d[..., :2], seq.points_2d, atol=1e-9)
    # the same numbers as reading the .mat directly
    np.testing.assert_array_equal(seq.points_3d, load_cmu_mat(cmu_dir / "drink.mat").points_3d)


def test_known_sizes(cmu_dir):
    sizes = {"drink": (1102, 41), "pickup": (357, 41), "yoga": (307, 41), "stretch": (370, 41),
             "dance": (264, 75), "jaws_rearranged": (240, 91)}
    for name, (f, p) in sizes.items():
        path = cmu_dir / f"{name}.mat"
        if path.exists():
            seq = load_cmu_mat(path)
            assert (seq.n_frames, seq.n_points) == (f, p), name


def test_unknown_mat_layout_is_a_clear_error(tmp_path):
    import scipy.io

    path = tmp_path / "odd.mat"
    scipy.io.savemat(str(path), {"foo": np.zeros((3, 3))})
    with pytest.raises(DataFormatError, match=r"expected the Akhter layout .* got variables \['foo'\]"):
        load_cmu_mat(path)
