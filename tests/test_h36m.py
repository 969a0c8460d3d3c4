import pickle  # noqa: F401  (the VideoPose3D layout stores pickled dicts; the test writes one)

import h5py
import numpy as np
import pytest

from nrsfm.datasets import h36m
from nrsfm.datasets.synthetic import human_motion, ring_cameras
from nrsfm.geometry import project_perspective


# ------------------------------------------------------------------ fixtures in both public layouts
@pytest.fixture
def fake_h36m(tmp_path):
    """A tiny Human3.6M copy in the 3d-pose-baseline layout plus VideoPose3D npz files (same data)."""
    root = tmp_path / "h36m"
    cams = ring_cameras(0)
    world = human_motion("S9", "walking", 20, seed=0)  # (F, 17, 3) mm
    full = np.zeros((20, 32, 3))
    full[:, list(h36m.JOINTS_32_TO_17)] = world
    with h5py.File(tmp_path / "h36m_cams.h5", "w") as h5:
        pass
    root.mkdir()
    with h5py.File(root / "cameras.h5", "w") as h5:
        for c, cam in enumerate(cams, start=1):
            g = h5.create_group(f"subject9/camera{c}")
            g["R"] = cam.rotation.T  # stored transposed, as upstream
            g["T"] = cam.centre[:, None]
            g["f"] = cam.intrinsics[[0, 1], [0, 1]][:, None]
            g["c"] = cam.intrinsics[:2, 2][:, None]
            g["Name"] = np.array([ord(ch) for ch in h36m.CAMERA_IDS[c - 1]])[:, None]
    pos = root / "S9" / "MyPoses" / "3D_positions"
    pos.mkdir(parents=True)
    with h5py.File(pos / "Walking 1.h5", "w") as h5:
        h5["3D_positions"] = full.reshape(20, 96).T
    shdir = root / "S9" / "StackedHourglass"
    shdir.mkdir(parents=True)
    sh_truth = {}
    for c, cam in enumerate(cams, start=1):
        uv = project_perspective(cam.world_to_camera(world), cam.intrinsics)  # (F, 17, 2)
        sh = np.stack([uv[:, h36m.JOINT_NAMES.index(n)] for n in h36m.SH_JOINT_NAMES], axis=1)  # (F, 16, 2)
        with h5py.File(shdir / f"Walking_1.{h36m.CAMERA_IDS[c - 1]}.h5", "w") as h5:
            h5["poses"] = sh
        sh_truth[c] = uv
    np.savez(tmp_path / "data_3d_h36m.npz", positions_3d={"S9": {"Walking 1": full / 1000.0}})
    np.savez(tmp_path / "data_2d_h36m_gt.npz", positions_2d={"S9": {"Walking 1": [sh_truth[c] for c in (1, 2, 3, 4)]}},
             metadata={"layout_name": "h36m", "num_joints": 17})
    return root, tmp_path, world, cams, sh_truth


def test_baseline_layout_world_to_camera_and_projections(fake_h36m):
    root, _, world, cams, sh_truth = fake_h36m
    for inp in ("gt-ortho", "gt-persp", "sh"):
        seq = h36m.load_h36m_sequence(root, "S9", "Walking 1", 2, input=inp, stride=1, source_fps=10)
        np.testing.assert_allclose(seq.points_3d, cams[1].world_to_camera(world), atol=1e-9)
        assert seq.meta["action"] == "Walking" and seq.meta["subject"] == "S9" and seq.fps == 10
        if inp == "gt-ortho":
            np.testing.assert_allclose(seq.points_2d, seq.points_3d[..., :2], atol=1e-12)
        else:
            np.testing.assert_allclose(seq.points_2d[:, [j for j in range(17) if j != 9]],
                                       sh_truth[2][:, [j for j in range(17) if j != 9]], atol=1e-6)
    seq = h36m.load_h36m_sequence(root, "S9", "Walking 1", 1, input="sh", stride=1)
    assert seq.visibility[:, h36m.JOINT_NAMES.index("Neck/Nose")].max() == 0
    assert seq.visibility.sum() == 16 * seq.n_frames
    assert h36m.load_h36m_sequence(root, 9, "Walking 1", 1, stride=2).n_frames == 10


def test_videopose3d_layout_matches_baseline_layout(fake_h36m):
    root, tmp, world, cams, _ = fake_h36m
    vp = h36m.load_videopose3d(tmp / "data_3d_h36m.npz", root / "cameras.h5", stride=1, input="gt-persp")
    assert len(vp) == 4
    for seq in vp:
        c = int(seq.meta["camera"])
        ref = h36m.load_h36m_sequence(root, "S9", "Walking 1", c, input="gt-persp", stride=1)
        np.testing.assert_allclose(seq.points_3d, ref.points_3d, atol=1e-6)
        np.testing.assert_allclose(seq.points_2d, ref.points_2d, atol=1e-6)
    sh = h36m.load_videopose3d(tmp / "data_3d_h36m.npz", root / "cameras.h5", stride=1, input="sh",
                               path_2d=tmp / "data_2d_h36m_gt.npz")
    assert sh[0].meta["input"] == "sh" and sh[0].n_points == 17


def test_missing_files_are_clear_errors(fake_h36m, tmp_path):
    root = fake_h36m[0]
    with pytest.raises(FileNotFoundError, match="known for S9"):
        h36m.load_h36m_sequence(root, "S9", "Eating", 1)
    with pytest.raises(ValueError, match="camera: expected 1, 2, 3 or 4"):
        h36m.load_h36m_sequence(root, "S9", "Walking 1", 5)
    with pytest.raises(ValueError, match="input: expected one of"):
        h36m.load_h36m_sequence(root, "S9", "Walking 1", 1, input="gt")


def test_sh_joint_mapping_is_a_permutation_plus_neck():
    idx = [i for i in h36m.SH_TO_17 if i >= 0]
    assert sorted(idx) == list(range(16))
    assert h36m.SH_TO_17[h36m.JOINT_NAMES.index("Neck/Nose")] == -1
    assert h36m.SH_TO_17[0] == h36m.SH_JOINT_NAMES.index("Hip")


# ------------------------------------------------------------------ real data
@pytest.mark.realdata
def test_s9_walking_camera1_projection_matches_hourglass_hip(h36m_dir):
    seq = h36m.load_h36m_sequence(h36m_dir, "S9", "Walking", 1, input="gt-persp", stride=1, source_fps=10)
    sh = h36m.load_h36m_sequence(h36m_dir, "S9", "Walking", 1, input="sh", stride=1, source_fps=10)
    hip = h36m.JOINT_NAMES.index("Hip")
    dist = np.linalg.norm(seq.points_2d[:, hip] - sh.points_2d[:, hip], axis=1)
    assert dist.mean() < 12.0, f"mean hip distance {dist.mean():.1f} px"
    # every visible SH joint is near the projection too (the detector is good, the cameras right)
    vis = sh.visibility > 0
    assert np.median(np.linalg.norm(seq.points_2d - sh.points_2d, axis=2)[vis]) < 20.0


@pytest.mark.realdata
def test_real_loader_split_and_shapes(h36m_dir):
    seqs = h36m.load_h36m(h36m_dir, ["S9"], actions=("Walking",), stride=1, source_fps=10)
    assert len(seqs) == 8  # 2 sub-actions x 4 cameras
    with pytest.raises(ValueError, match=r"expected Human3.6M files of subjects \['S99'\], found none; subjects "
                                         r"present: \[.*'S9'"):
        h36m.load_h36m(h36m_dir, ["S99"])  # returned an empty list
    with pytest.raises(ValueError, match=r"actions \['Flying'\], found none"):
        h36m.load_h36m(h36m_dir, ["S9"], actions=("Flying",))
    for s in seqs:
        assert s.n_points == 17 and s.points_3d[..., 2].min() > 1000  # in front of the camera, mm
        bones = np.linalg.norm(s.points_3d[:, 1] - s.points_3d[:, 2], axis=1)  # RHip-RKnee
        assert bones.std() < 1.0  # a rigid bone in real mocap


def test_world_loader_gives_the_files_world_frame(fake_h36m):
    root, _, world, cams, _ = fake_h36m
    np.testing.assert_allclose(h36m.load_h36m_world(root, "S9", "Walking 1", stride=1), world, atol=1e-9)
    np.testing.assert_allclose(h36m.load_h36m_world(root, 9, "Walking 1", stride=2), world[::2], atol=1e-9)
    with pytest.raises(FileNotFoundError, match="known for S9"):
        h36m.load_h36m_world(root, "S9", "Eating", stride=1)
