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


def _aflw_release(root, n: int, seed: int = 0):
    """AFLW2000-3D's release files under ``root/aflw2000`` with ``n`` random faces; returns the 3D array."""
    rng = np.random.default_rng(seed)
    folder = root / "aflw2000"
    folder.mkdir(parents=True)
    x3 = (rng.normal(size=(n, 3, 68)) * 20 + 100).astype(np.float32)
    x2 = (x3[:, :2] + rng.normal(size=(n, 2, 68)) * 3).astype(np.float32)
    yaw = np.linspace(-100, 100, n).astype(np.float32)
    np.save(folder / "AFLW2000-3D.pts68.npy", x3)
    np.save(folder / "AFLW2000-3D-Reannotated.pts68.npy", x2)
    np.save(folder / "AFLW2000-3D.pose.npy", yaw)
    return x3, x2, yaw


@pytest.mark.parametrize("n", [40, 2000])  # this copy's 1,500 faces or the release's 2,000: split by index alike
def test_aflw2000_loader_reads_the_release_layout_and_splits_by_index(tmp_path, n):
    from nrsfm.datasets.aflw import face_yaw, load_aflw2000, split_aflw2000, yaw_band

    x3, x2, yaw = _aflw_release(tmp_path, n)
    fitted = load_aflw2000(tmp_path)
    assert fitted.points_2d.shape == (n, 68, 2) and fitted.points_3d.shape == (n, 68, 3)
    np.testing.assert_allclose(fitted.points_3d, x3.transpose(0, 2, 1), rtol=1e-6)
    np.testing.assert_allclose(fitted.points_2d, fitted.points_3d[..., :2])  # orthographic: the 3D's own x, y
    np.testing.assert_allclose(face_yaw(fitted), yaw, rtol=1e-5)
    re = load_aflw2000(tmp_path, input="reannotated")
    np.testing.assert_allclose(re.points_2d, x2.transpose(0, 2, 1), rtol=1e-6)
    # the 3D is moved onto the hand-corrected 2D (same x, y mean), its shape unchanged
    np.testing.assert_allclose(re.points_3d[..., :2].mean(1), re.points_2d.mean(1), atol=1e-3)
    np.testing.assert_allclose(re.points_3d - re.points_3d.mean(1, keepdims=True),
                               fitted.points_3d - fitted.points_3d.mean(1, keepdims=True), atol=1e-3)
    train, test = split_aflw2000(re)
    k = int(0.75 * n)
    assert train.n_frames == k and test.n_frames == n - k and test.meta["first_face"] == str(k)
    np.testing.assert_allclose(test.points_2d[0], re.points_2d[k])
    np.testing.assert_allclose(face_yaw(test), yaw[k:], rtol=1e-5)
    assert set(yaw_band(face_yaw(re))) == {"0-30", "30-60", "60-90"}
    with pytest.raises(DataFormatError, match="input: expected one of"):
        load_aflw2000(tmp_path, input="detected")


def test_aflw2000_bad_files_give_clear_errors(tmp_path):
    from nrsfm.datasets.aflw import load_aflw2000

    _aflw_release(tmp_path, 10)
    np.save(tmp_path / "aflw2000" / "AFLW2000-3D.pose.npy", np.zeros(9, np.float32))
    with pytest.raises(DataFormatError, match="expected one yaw per face"):
        load_aflw2000(tmp_path)
    (tmp_path / "aflw2000" / "AFLW2000-3D.pose.npy").unlink()
    with pytest.raises(DataFormatError, match="missing \\['AFLW2000-3D.pose.npy'\\]"):
        load_aflw2000(tmp_path)


def test_aflw2000_real_faces(real_data):
    root = real_data("aflw2000").parent
    from nrsfm.datasets.aflw import load_aflw2000, split_aflw2000

    seq = load_aflw2000(root, input="reannotated")
    train, test = split_aflw2000(seq)
    assert seq.n_points == 68 and train.n_frames == int(0.75 * seq.n_frames)
    # hand-corrected 2D lies near the fitted landmarks' projection (a few pixels), not on it
    gap = np.linalg.norm(seq.points_2d - load_aflw2000(root).points_2d, axis=2).mean()
    assert 1.0 < gap < 20.0


def _surreal_info(path, frames: int = 5, seed: int = 0):
    """A SURREAL *_info.mat with a known camera: joints2D made by SURREAL's own projection of joints3D."""
    from nrsfm.datasets.surreal import INTRINSICS, surreal_camera

    rng = np.random.default_rng(seed)
    cam_loc = np.array([6.7, -0.98, -1.93])
    world = rng.normal(size=(frames, 24, 3)) * 0.3 + np.array([0.05, -1.0, -1.9])
    rot, t = surreal_camera(cam_loc)
    cam = world @ rot.T + t
    uv = cam @ INTRINSICS.T
    j2 = np.round(uv[..., :2] / uv[..., 2:])
    scipy.io.savemat(str(path), {"joints3D": world.transpose(2, 1, 0), "joints2D": j2.transpose(2, 1, 0),
                                 "camLoc": cam_loc[:, None], "zrot": np.zeros((frames, 1))})
    return world, j2


def test_surreal_info_files_give_24_joints_in_the_camera_frame(tmp_path):
    from nrsfm.datasets.surreal import SMPL_JOINTS, load_surreal_info

    world, j2 = _surreal_info(tmp_path / "01_01_c0001_info.mat")
    seq = load_surreal_info(tmp_path / "01_01_c0001_info.mat")
    assert seq.points_3d.shape == (5, 24, 3) and seq.projection == "perspective"
    assert seq.joint_names == SMPL_JOINTS and seq.meta["clip"] == "01_01_c0001"
    proj = seq.points_3d @ seq.intrinsics.T
    np.testing.assert_allclose(proj[..., :2] / proj[..., 2:], j2, atol=0.5 + 1e-9)  # rounded pixels
    assert (seq.points_3d[..., 2] > 0).all()  # in front of the camera, millimetres
    # Table 4's protocol on skeletons: the clips of a split folder, turned at random about the vertical
    (tmp_path / "surreal" / "train").mkdir(parents=True)
    _surreal_info(tmp_path / "surreal" / "train" / "a_info.mat", seed=1)
    clips = load_surreal("train", tmp_path)
    assert len(clips) == 1 and clips[0].n_points == 24 and clips[0].projection == "orthographic"
    world_mm = (world := _surreal_info(tmp_path / "b_info.mat", seed=1)[0]) * 1000.0
    centred = clips[0].points_3d - clips[0].points_3d.mean(1, keepdims=True)  # a rotation of the world's joints
    np.testing.assert_allclose(np.linalg.norm(centred, axis=2),
                               np.linalg.norm(world_mm - world_mm.mean(1, keepdims=True), axis=2), rtol=1e-9)
    assert world.shape == (5, 24, 3)


def test_surreal_info_real_sample_reprojects_within_a_pixel(real_data):
    path = real_data("surreal", "sample", "01_01_c0001_info.mat")
    from nrsfm.datasets.surreal import load_surreal_info

    seq = load_surreal_info(path)
    proj = seq.points_3d @ seq.intrinsics.T
    err = np.linalg.norm(proj[..., :2] / proj[..., 2:] - seq.points_2d, axis=2)
    assert seq.n_points == 24 and err.max() < 1.0
    # a body of plausible size in millimetres, metres in front of the camera
    height = np.ptp(seq.points_3d[..., 1], axis=1)
    assert 1000 < height.mean() < 2200 and 3000 < seq.points_3d[..., 2].mean() < 12000
