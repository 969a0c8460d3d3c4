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
