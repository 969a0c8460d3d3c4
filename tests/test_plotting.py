import numpy as np

from nrsfm.datasets.synthetic import human_sequences
from nrsfm.metrics import e3d_per_frame
from nrsfm.plotting import plot_error_curve, plot_reconstruction


def test_plots_are_written(tmp_path):
    seq = human_sequences(("S1",), ("walking",), (1,), n_frames=10, missing=0.1)[0]
    noisy = seq.points_3d + 10 * np.random.default_rng(0).standard_normal(seq.points_3d.shape)
    p = plot_reconstruction(seq, noisy, tmp_path / "rec.png", frames=[0, 5])
    assert p.stat().st_size > 5000 and p.read_bytes()[:4] == b"\x89PNG"
    q = plot_error_curve({"noisy": e3d_per_frame(noisy, seq.points_3d)}, tmp_path / "curve.png")
    assert q.stat().st_size > 2000
    r = plot_reconstruction(seq.replace(points_3d=None), None, tmp_path / "input_only.png")
    assert r.exists()


def test_plots_refuse_mismatched_input_before_drawing(tmp_path):
    import pytest

    from nrsfm import ValidationError

    seq = human_sequences(("S1",), ("walking",), (1,), n_frames=10)[0]
    with pytest.raises(ValidationError, match=r"points_3d: expected \(F, P, 3\) = \(10, 17, 3\)"):
        plot_reconstruction(seq, seq.points_3d[:, :5], tmp_path / "a.png")  # was numpy's LinAlgError
    with pytest.raises(ValidationError, match=r"frames: expected indices in \[0, 9\], got \[3, 10\]"):
        plot_reconstruction(seq, seq.points_3d, tmp_path / "b.png", frames=[3, 10])
    with pytest.raises(ValidationError, match="curves: expected at least one named curve"):
        plot_error_curve({}, tmp_path / "c.png")
    assert not list(tmp_path.iterdir())
