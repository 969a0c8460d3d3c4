import numpy as np
import pytest

from nrsfm import Sequence, ValidationError
from nrsfm.datasets.synthetic import lowrank_sequence


def test_valid_sequence_is_frozen_and_read_only(rng):
    seq = Sequence(points_2d=rng.standard_normal((5, 4, 2)))
    assert (seq.n_frames, seq.n_points) == (5, 4)
    with pytest.raises(Exception):
        seq.name = "x"
    with pytest.raises(ValueError):
        seq.points_2d[0, 0, 0] = 1.0


@pytest.mark.parametrize("shape, hint", [((2, 17, 120), "3 x P x F"), ((3, 17, 120), "3 x P x F"),
                                         ((240, 17), "2F x P"), ((10, 2, 17), "channel-first")])
def test_wrong_layout_names_field_shapes_and_hint(shape, hint):
    with pytest.raises(ValidationError, match=rf"points_2d: expected \(F, P, 2\), got .*{shape[0]}.*{hint}"):
        Sequence(points_2d=np.zeros(shape))


def test_nan_at_visible_point_raises_and_is_allowed_when_missing(rng):
    p2 = rng.standard_normal((4, 3, 2))
    p2[1, 2] = np.nan
    with pytest.raises(ValidationError, match="frame 1, point 2.*visibility = 0"):
        Sequence(points_2d=p2)
    vis = np.ones((4, 3))
    vis[1, 2] = 0
    seq = Sequence(points_2d=p2, visibility=vis)
    assert np.isfinite(seq.points_2d).all() and seq.points_2d[1, 2, 0] == 0
    assert seq.missing_fraction == pytest.approx(1 / 12)
    assert not seq.is_complete


def test_visibility_and_ground_truth_shapes_are_checked(rng):
    p2 = rng.standard_normal((4, 3, 2))
    with pytest.raises(ValidationError, match=r"visibility: expected \(F, P\) = \(4, 3\), got \(3, 4\)"):
        Sequence(points_2d=p2, visibility=np.ones((3, 4)))
    with pytest.raises(ValidationError, match=r"visibility: expected values in \[0, 1\]"):
        Sequence(points_2d=p2, visibility=np.full((4, 3), 2.0))
    with pytest.raises(ValidationError, match=r"points_3d: expected \(F, P, 3\)"):
        Sequence(points_2d=p2, points_3d=np.zeros((4, 3, 2)))
    with pytest.raises(ValidationError, match="projection"):
        Sequence(points_2d=p2, projection="fisheye")
    with pytest.raises(ValidationError, match="1-based"):
        Sequence(points_2d=p2, edges=np.array([[1, 3]]))
    with pytest.raises(ValidationError, match="joint_names"):
        Sequence(points_2d=p2, joint_names=("a", "b"))
    with pytest.raises(ValidationError, match="points_2d: expected real numbers, got complex"):
        Sequence(points_2d=p2 + 1j)
    for fps in (0.0, -5.0, np.nan, [10.0, 20.0]):
        with pytest.raises(ValidationError, match="fps: expected one positive frame rate"):
            Sequence(points_2d=p2, fps=fps)
    assert Sequence(points_2d=p2, fps=np.array(25)).fps == 25.0
    for bad, what in ((np.zeros((4, 3, 3)), r"\|R R\^T - I\| = 1"), (-np.eye(3)[None].repeat(4, 0), "det -1")):
        with pytest.raises(ValidationError, match=f"camera_rotations: expected rotation matrices.*{what}"):
            Sequence(points_2d=p2, camera_rotations=bad)


def test_save_load_roundtrip_without_pickle(tmp_path):
    seq = lowrank_sequence(20, 8, 2, missing=0.2, seed=3).replace(
        edges=np.array([[0, 1], [1, 2]]), joint_names=tuple("abcdefgh"), fps=25.0, meta={"k": "v"})
    path = seq.save(tmp_path / "s.npz")
    with np.load(path, allow_pickle=False) as data:  # loads without pickle
        assert "points_2d" in data.files
    back = Sequence.load(path)
    for key in ("points_2d", "visibility", "points_3d", "camera_rotations", "edges"):
        np.testing.assert_array_equal(getattr(back, key), getattr(seq, key))
    assert back.joint_names == seq.joint_names and back.fps == 25.0 and back.meta["k"] == "v"
    assert back.name == seq.name


def test_save_never_overwrites_without_permission(tmp_path):
    seq = lowrank_sequence(5, 4, 1)
    path = seq.save(tmp_path / "s.npz")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="--force"):
        lowrank_sequence(6, 4, 1).save(path)
    assert path.read_bytes() == before
    lowrank_sequence(6, 4, 1).save(path, overwrite=True)
    assert Sequence.load(path).n_frames == 6


def test_measurement_matrix_interleaves_rows(rng):
    p2 = rng.standard_normal((3, 5, 2))
    w = Sequence(points_2d=p2).measurement_matrix()
    assert w.shape == (6, 5)
    np.testing.assert_array_equal(w[2], p2[1, :, 0])
    np.testing.assert_array_equal(w[3], p2[1, :, 1])


def test_select_frames_keeps_all_fields():
    seq = lowrank_sequence(10, 5, 2, missing=0.1, seed=1)
    sub = seq.select_frames(slice(2, 6))
    assert sub.n_frames == 4
    np.testing.assert_array_equal(sub.points_3d, seq.points_3d[2:6])
    np.testing.assert_array_equal(sub.camera_rotations, seq.camera_rotations[2:6])


def test_select_points_keeps_names_and_renumbers_edges():
    seq = lowrank_sequence(6, 5, 2, missing=0.1, seed=1).replace(
        joint_names=("a", "b", "c", "d", "e"), edges=np.array([[0, 1], [1, 2], [2, 4], [3, 4]]))
    sub = seq.select_points(np.array([True, False, True, True, True]))
    assert sub.joint_names == ("a", "c", "d", "e")
    np.testing.assert_array_equal(sub.edges, [[1, 3], [2, 3]])  # edges through the dropped point go
    np.testing.assert_array_equal(sub.points_2d, seq.points_2d[:, [0, 2, 3, 4]])
    np.testing.assert_array_equal(sub.visibility, seq.visibility[:, [0, 2, 3, 4]])
    np.testing.assert_array_equal(sub.points_3d, seq.points_3d[:, [0, 2, 3, 4]])
    np.testing.assert_array_equal(sub.camera_rotations, seq.camera_rotations)


def test_to_weak_perspective_normalises_pixels_by_the_intrinsics():
    from nrsfm.datasets.synthetic import human_sequences

    seq = human_sequences(("S9",), ("walking",), (2,), n_frames=20, projection="perspective")[0]
    k = np.array([[1100.0, 3.0, 500.0], [0.0, 1150.0, 520.0], [0.0, 0.0, 1.0]])  # with skew
    seq = seq.replace(points_2d=np.einsum("ij,fpj->fpi", k, seq.points_3d / seq.points_3d[..., 2:])[..., :2],
                      intrinsics=k)
    weak = seq.to_weak_perspective()
    assert weak.projection == "orthographic" and weak.intrinsics is None and "weak_perspective" in weak.meta
    x = seq.points_3d
    np.testing.assert_allclose(weak.points_2d, x[..., :2] / x[..., 2:], atol=1e-12)  # (X / Z, Y / Z)
    np.testing.assert_allclose(weak.points_3d, x / x[..., 2].mean(axis=1)[:, None, None], rtol=1e-12)
    with pytest.raises(ValidationError, match="expected perspective tracks, got orthographic"):
        weak.to_weak_perspective()
    with pytest.raises(ValidationError, match="no intrinsics"):
        seq.replace(intrinsics=None).to_weak_perspective()
    with pytest.raises(ValidationError, match="in front of the camera"):
        seq.replace(points_3d=-x).to_weak_perspective()
