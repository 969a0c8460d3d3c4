"""Rendered stand-in images (nrsfm.datasets.render) and video frames in the public layouts (nrsfm.datasets.frames)."""

import numpy as np
import pytest

from nrsfm.datasets import h36m
from nrsfm.datasets.faces import load_300vw
from nrsfm.datasets.frames import FrameImages, h36m_frames, vw300_frames
from nrsfm.datasets.render import LEFT, RIGHT, limb_colours, render_capsules, render_sequence
from nrsfm.datasets.synthetic import face_sequences, human_sequences
from nrsfm.errors import DataFormatError, ValidationError
from nrsfm.sequence import Sequence

PIL = pytest.importorskip("PIL.Image")


def _colour_near(img, rgb, tol=60):
    return (np.abs(img.astype(int) - (255 * np.asarray(rgb) * 0.35).astype(int)).max(-1) <= tol * 2).sum()


def test_limbs_are_coloured_by_side_and_the_nearer_capsule_wins():
    seq = human_sequences(["S1"], n_frames=5, takes=1, seed=0, motions=("walking",))[0]
    colours = limb_colours(seq.joint_names, seq.edges)
    names = seq.joint_names
    for (i, j), c in zip(seq.edges, colours):
        side = {names[i][0], names[j][0]} & {"L", "R"}
        expected = LEFT if side == {"L"} else RIGHT if side == {"R"} else None
        if expected is not None:
            np.testing.assert_allclose(c, expected)
    img = render_sequence(seq, size=48)
    assert img.shape == (5, 48, 48, 3) and img.dtype == np.uint8
    red = (img[..., 0] > img[..., 2] + 40).sum()
    blue = (img[..., 2] > img[..., 0] + 40).sum()
    assert red > 50 and blue > 50  # both sides are drawn, distinguishable by colour

    # two crossing bars: the one with the smaller z is in front at the crossing
    pts = np.array([[[-1, 0, 0.0], [1, 0, 0.0], [0, -1, 5.0], [0, 1, 5.0]]])
    edges = np.array([[0, 1], [2, 3]])
    im = render_capsules(pts, edges, np.array([LEFT, RIGHT]), size=32)[0]
    assert im[16, 16, 0] > im[16, 16, 2]  # the red bar (z = 0) hides the blue one (z = 5)
    pts[0, :2, 2] = 10.0
    im = render_capsules(pts, edges, np.array([LEFT, RIGHT]), size=32)[0]
    assert im[16, 16, 2] > im[16, 16, 0]
    assert tuple(im[0, 0]) == (31, 31, 31)  # background


def test_render_refuses_bad_input():
    with pytest.raises(ValidationError, match=r"expected \(F, P, 3\)"):
        render_capsules(np.zeros((2, 4)), np.array([[0, 1]]), np.zeros((1, 3)))
    with pytest.raises(ValidationError, match="indexing 2 points"):
        render_capsules(np.zeros((1, 2, 3)), np.array([[0, 5]]), np.zeros((1, 3)))
    seq = Sequence(points_2d=np.zeros((3, 4, 2)), name="no3d")
    with pytest.raises(ValidationError, match="needs points_3d"):
        render_sequence(seq)


def test_faces_render_with_a_hue_per_contour():
    face = face_sequences(1, 3, seed=0)[0]
    img = render_sequence(face, size=40)
    assert img.shape == (3, 40, 40, 3) and (img.max(-1) > 60).sum() > 100


def _write_frames(folder, n, size=(120, 90), colour=(200, 30, 30)):
    folder.mkdir(parents=True)
    for k in range(1, n + 1):
        PIL.new("RGB", size, colour).save(folder / f"{k:06d}.jpg")


def test_h36m_frames_in_the_extracted_video_layout(tmp_path):
    cam = h36m.Camera(rotation=np.eye(3), centre=np.zeros(3), focal=np.array([100.0, 100.0]),
                      principal=np.array([60.0, 45.0]))
    x3 = np.tile(np.array([[-100.0, -200, 2000], [100, 200, 2000], [0, 0, 2100]]), (4, 1, 1))
    seq = Sequence(points_2d=x3[..., :2], points_3d=x3, name="S9/Walking 1/cam2",
                   meta={"dataset": "h36m", "subject": "S9", "subaction": "Walking 1", "camera": "2"})
    folder = tmp_path / "images" / "S9" / f"Walking 1.{h36m.CAMERA_IDS[1]}"
    _write_frames(folder, 16)
    frames = h36m_frames(tmp_path, seq, stride=5, size=32, cameras={("S9", 2): cam})
    assert len(frames) == 4 and frames.shape == (4, 32, 32, 3)
    assert [p.name for p in frames.paths] == ["000001.jpg", "000006.jpg", "000011.jpg", "000016.jpg"]
    np.testing.assert_allclose(frames.centres[0], [60, 45])  # the box of the projected joints: 50..70, 35..55
    im = frames[np.array([3, 0])]
    assert im.shape == (2, 32, 32, 3) and im[:, 16, 16, 0].min() > 150  # the red frame, cropped
    with pytest.raises(DataFormatError, match="000016.jpg: expected 4 frames"):
        (folder / "000016.jpg").unlink()
        h36m_frames(tmp_path, seq, stride=5, size=32, cameras={("S9", 2): cam})
    with pytest.raises(DataFormatError, match="expected a folder of extracted frames"):
        h36m_frames(tmp_path / "nowhere", seq, stride=5, cameras={("S9", 2): cam})


def test_300vw_frames_are_cropped_on_the_landmarks(tmp_path):
    face = face_sequences(1, 3)[0].points_3d * 0.2 + np.array([300.0, 200.0, 0.0])
    d3 = tmp_path / "300vw-3d" / "007"
    d3.mkdir(parents=True)
    for t, shape in enumerate(face):
        np.save(d3 / f"{t + 5:06d}.npy", shape)  # annotated frames 5, 6, 7
    seq = load_300vw("007", tmp_path)
    _write_frames(tmp_path / "300vw" / "007" / "frames", 7, size=(640, 480))
    frames = vw300_frames(tmp_path, "007", seq, size=24)
    assert [p.name for p in frames.paths] == ["000005.jpg", "000006.jpg", "000007.jpg"]
    np.testing.assert_allclose(frames.centres, face.mean(axis=1)[:, :2], atol=1e-2)
    assert frames[np.arange(3)].shape == (3, 24, 24, 3)
    with pytest.raises(ValidationError, match="expected \\(2, 2\\) centres"):
        FrameImages(frames.paths[:2], np.zeros((3, 2)), np.ones(2))
