"""Loaders of 300-VW (2D .pts and the 3D landmark set) and of SURREAL vertex exports, on files in their layouts."""

import numpy as np
import pytest
import scipy.io

from nrsfm.datasets.faces import list_300vw, load_300vw, read_pts, split_300vw
from nrsfm.datasets.surreal import load_surreal
from nrsfm.datasets.synthetic import face_sequences
from nrsfm.errors import DataFormatError


def _write_pts(path, pts):
    body = "\n".join(" ".join(f"{v:.3f}" for v in p) for p in pts)
    path.write_text(f"version: 1\nn_points:  {len(pts)}\n{{\n{body}\n}}\n")


@pytest.fixture
def vw_root(tmp_path):
    face = face_sequences(1, 6)[0].points_3d + 200.0  # (6, 68, 3)
    for video, kind in (("001", "pts"), ("002", "npy"), ("010", "mat")):
        annot = tmp_path / "300vw" / video / "annot"
        annot.mkdir(parents=True)
        d3 = tmp_path / "300vw-3d" / video
        d3.mkdir(parents=True)
        for t, shape in enumerate(face):
            _write_pts(annot / f"{t + 1:06d}.pts", shape[:, :2])
            if kind == "pts":
                _write_pts(d3 / f"{t + 1:06d}.pts", shape)
            elif kind == "npy":
                np.save(d3 / f"{t + 1:06d}.npy", shape)
            else:
                scipy.io.savemat(str(d3 / f"{t + 1:06d}.mat"), {"pts_3d": shape.T})  # (3, 68) also accepted
    return tmp_path, face


def test_300vw_2d_and_3d_layouts(vw_root):
    root, face = vw_root
    assert list_300vw(root) == ["001", "002", "010"]
    centred = face - face.mean(axis=1, keepdims=True)
    for video in ("001", "002", "010"):
        seq = load_300vw(video, root)
        assert seq.points_3d.shape == (6, 68, 3) and seq.meta["input"] == "3d-xy"
        np.testing.assert_allclose(seq.points_3d, centred, atol=2e-3)
        np.testing.assert_allclose(seq.points_2d, centred[..., :2], atol=2e-3)
    assert load_300vw("001", root, require_3d=False).meta["input"] == "3d-xy"  # the 3D is used where present
    (root / "300vw-3d" / "001").rename(root / "300vw-3d" / "x001")
    two_d = load_300vw("001", root, require_3d=False)
    assert two_d.meta["input"] == "annot" and two_d.points_3d is None
    np.testing.assert_allclose(two_d.points_2d, face[..., :2], atol=2e-3)  # the .pts pixels as written
    assert split_300vw(["1", "2", "3", "4", "5"], 2, 1) == (["1", "3"], ["2"])


def test_300vw_bad_files_give_clear_errors(vw_root, tmp_path):
    root, _ = vw_root
    bad = tmp_path / "bad.pts"
    bad.write_text("version: 1\nn_points: 68\n{\n1 2\n}\n")
    with pytest.raises(DataFormatError, match="expected 68 points of 2 coordinates"):
        read_pts(bad)
    with pytest.raises(DataFormatError, match="expected its 3D landmarks"):
        load_300vw("999", root)


def test_surreal_export_layout(tmp_path):
    rng = np.random.default_rng(0)
    for split in ("train", "test"):
        (tmp_path / "surreal" / split).mkdir(parents=True)
        for clip in ("a", "b"):
            np.savez(tmp_path / "surreal" / split / f"{clip}.npz", vertices=rng.standard_normal((5, 40, 3)))
    seqs = load_surreal("train", tmp_path)
    assert [s.name for s in seqs] == ["surreal-train-a", "surreal-train-b"]
    s = seqs[0]
    assert s.points_3d.shape == (5, 40, 3) and s.projection == "orthographic"
    np.testing.assert_allclose(s.points_2d, s.points_3d[..., :2])
    np.testing.assert_allclose(s.points_3d.mean(axis=1), 0, atol=1e-9)
    with np.load(tmp_path / "surreal" / "train" / "a.npz") as z:  # a rigid motion of the mesh, in millimetres
        v = z["vertices"] * 1000.0
    d_in = np.linalg.norm(v[:, :, None] - v[:, None], axis=-1)
    d_out = np.linalg.norm(s.points_3d[:, :, None] - s.points_3d[:, None], axis=-1)
    np.testing.assert_allclose(d_out, d_in, rtol=1e-9, atol=1e-6)
    np.savez(tmp_path / "surreal" / "test" / "c.npz", verts=np.zeros((2, 3, 3)))
    with pytest.raises(DataFormatError, match="expected an array 'vertices'"):
        load_surreal("test", tmp_path)
    with pytest.raises(DataFormatError, match="split: expected one of"):
        load_surreal("val", tmp_path)
