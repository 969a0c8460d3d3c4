import numpy as np
import pytest

from nrsfm.datasets import h36m
from nrsfm.datasets.synthetic import (MOTIONS, face_sequences, human_motion, human_sequences, lowrank_sequence,
                                      surface_sequence)
from nrsfm.geometry import project_perspective


def test_lowrank_is_deterministic_and_low_rank():
    a = lowrank_sequence(40, 12, 3, seed=7)
    b = lowrank_sequence(40, 12, 3, seed=7)
    np.testing.assert_array_equal(a.points_2d, b.points_2d)
    assert not np.array_equal(a.points_2d, lowrank_sequence(40, 12, 3, seed=8).points_2d)
    obj = np.einsum("fpi,fij->fpj", a.points_3d, a.camera_rotations)  # object frame
    sv = np.linalg.svd(obj.reshape(40, -1), compute_uv=False)
    assert sv[3] < 1e-10 * sv[0] and sv[2] > 1e-3 * sv[0]  # rank exactly 3
    np.testing.assert_allclose(a.points_3d[..., :2], a.points_2d)


def test_lowrank_noise_and_missing():
    seq = lowrank_sequence(50, 20, 2, noise=0.01, missing=0.2, seed=1)
    assert 0.15 < seq.missing_fraction < 0.25
    vis = seq.visibility > 0
    err = np.abs(seq.points_3d[..., :2] - seq.points_2d)[vis]
    assert 0.003 < err.mean() < 0.02


def test_human_bones_are_rigid_per_subject_and_differ_between_subjects():
    def bones(subject, motion):
        pos = human_motion(subject, motion, 60, seed=0)
        return np.stack([np.linalg.norm(pos[:, j] - pos[:, p], axis=1) for j, p in enumerate(h36m.PARENTS) if p >= 0],
                        axis=1)  # (F, 16)

    for motion in MOTIONS:
        b = bones("S1", motion)
        np.testing.assert_allclose(b, np.broadcast_to(b[0], b.shape), rtol=1e-9)
    np.testing.assert_allclose(bones("S1", "walking")[0], bones("S1", "bending")[0])
    assert np.abs(bones("S1", "walking")[0] - bones("S9", "walking")[0]).max() > 5.0  # mm


def test_human_cameras_views_and_projection():
    seqs = human_sequences(("S9",), ("walking", "sitting_down"), n_frames=30, projection="perspective")
    assert len(seqs) == 8 and {s.meta["camera"] for s in seqs} == {"1", "2", "3", "4"}
    for s in seqs:
        assert s.points_3d[..., 2].min() > 2000  # in front of every camera, mm
        np.testing.assert_allclose(s.points_2d, project_perspective(s.points_3d, s.intrinsics), atol=1e-9)
        assert s.joint_names == h36m.JOINT_NAMES and s.edges.shape == (16, 2)
        assert (s.points_2d > -500).all() and (s.points_2d < 1500).all()  # roughly inside a 1000 px image
    # the same motion seen by two cameras: same world pose, different camera frames
    a, b = seqs[0], seqs[1]
    assert not np.allclose(a.points_3d, b.points_3d)
    ortho = human_sequences(("S9",), ("walking",), (1,), n_frames=30, noise=5.0, missing=0.1)[0]
    assert ortho.projection == "orthographic" and 0.05 < ortho.missing_fraction < 0.15
    vis = ortho.visibility > 0
    assert 2.0 < np.abs(ortho.points_2d - ortho.points_3d[..., :2])[vis].mean() < 10.0


def test_motion_families_move_differently():
    poses = {m: human_motion("S1", m, 80, seed=0) for m in MOTIONS}
    centred = {m: p - p[:, :1] for m, p in poses.items()}
    sitting = centred["sitting_down"]
    # sitting down brings the hips towards the knees' height at some point
    assert (sitting[:, 2, 1] - sitting[:, 0, 1]).max() > -250
    for m in MOTIONS:
        assert np.ptp(centred[m], axis=0).max() > 100, m  # every family has real articulation


def test_faces_and_surfaces():
    faces = face_sequences(2, 50, seed=0)
    assert faces[0].n_points == 68 and faces[0].edges is not None
    assert not np.allclose(faces[0].points_3d[0], faces[1].points_3d[0])
    np.testing.assert_allclose(faces[0].points_3d[..., :2], faces[0].points_2d)
    surf = surface_sequence(10)
    assert surf.n_points >= 3000
    np.testing.assert_allclose(surf.points_3d[..., :2], surf.points_2d)


def test_bad_arguments():
    with pytest.raises(ValueError, match="missing"):
        lowrank_sequence(10, 5, 1, missing=1.5)
    with pytest.raises(ValueError, match="motion"):
        human_motion("S1", "dancing")
    for make in (lambda **k: lowrank_sequence(10, 5, 1, **k), lambda **k: face_sequences(1, 10, **k),
                 lambda **k: human_sequences(("S1",), ("walking",), (1,), n_frames=10, **k),
                 lambda **k: surface_sequence(10, 6, 4, **k)):
        for noise in (-1.0, np.nan, np.inf):
            with pytest.raises(ValueError, match="noise: expected a finite standard deviation >= 0"):
                make(noise=noise)
    for make in (lambda n: face_sequences(1, n), lambda n: surface_sequence(n),
                 lambda n: human_sequences(("S1",), ("walking",), (1,), n_frames=n)):
        with pytest.raises(ValueError, match="expected n_frames >= 1, got 0"):
            make(0)


def test_orbit_sequence_turns_the_camera_about_the_vertical_axis():
    from nrsfm.datasets.synthetic import human_motion, orbit_sequence

    world = human_motion("S1", "walking", 40, seed=0)  # (F, 17, 3), y up
    seq = orbit_sequence(world, 90.0, up=1, elevation_deg=0.0, name="orbit")
    rot = seq.camera_rotations
    np.testing.assert_allclose(np.einsum("fij,fkj->fik", rot, rot), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0)
    np.testing.assert_allclose(seq.points_2d, seq.points_3d[..., :2])
    # the camera's up is the world's up at zero elevation, and the view turns by 90 degrees over the sequence
    np.testing.assert_allclose(rot[:, 1], np.broadcast_to([0.0, 1.0, 0.0], (40, 3)), atol=1e-12)
    np.testing.assert_allclose(abs(rot[0, 2] @ rot[-1, 2]), 0.0, atol=1e-12)
    # a z-up copy of the same motion gives the same sequence
    z_up = world[..., [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(orbit_sequence(z_up, 90.0, up=2, elevation_deg=0.0).points_3d, seq.points_3d,
                               atol=1e-9)
    from nrsfm.errors import ValidationError

    with pytest.raises(ValidationError, match="up"):
        orbit_sequence(world, 30.0, up=0)
