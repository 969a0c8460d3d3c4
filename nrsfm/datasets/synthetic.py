"""Synthetic data that needs nothing outside the package, deterministic by seed.

- :func:`lowrank_sequence`: shapes from a `K`-shape basis seen by random
  orthographic cameras, with the answer known (solver tests). ``n_basis=1``
  gives a rigid object.
- :func:`human_sequences`: an articulated human on the Human3.6M 17-joint
  skeleton; several subjects (bone lengths vary), motion families, 4 cameras
  on a ring like Human3.6M, orthographic or perspective projection,
  detector-like noise, missing points. The embedded stand-in for Human3.6M.
- :func:`face_sequences`: 68-landmark faces with identity and expression
  deformation and head rotation. The stand-in for 300-VW.
- :func:`surface_sequence`: a dense deforming surface with thousands of points
  turning about the vertical axis. The stand-in for SURREAL.
- :func:`orbit_sequence`: any world-frame motion (real motion capture
  included) seen by an orthographic camera turning about the vertical axis:
  an NRSfM sequence with known 3D and cameras.

Randomness: every generator takes ``seed`` (int); per-sequence streams are
derived from the seed and the sequence's name, so a sequence does not change
when others are added or removed.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from nrsfm.datasets import h36m
from nrsfm.errors import ValidationError
from nrsfm.geometry import project_perspective, random_rotations
from nrsfm.sequence import Sequence


def rng_for(seed: int, *names: object) -> np.random.Generator:
    """A generator seeded by ``seed`` and a stable hash of ``names``."""
    keys = [int(seed)] + [zlib.crc32(str(n).encode()) for n in names]
    return np.random.default_rng(keys)


def _smooth_signal(rng: np.random.Generator, t: np.ndarray, n: int, n_harmonics: int = 3,
                   max_freq: float = 1.0) -> np.ndarray:
    """`(len(t), n)` smooth random signals in roughly [-1, 1] (sums of sinusoids)."""
    freq = rng.uniform(0.1, max_freq, size=(n_harmonics, n))
    phase = rng.uniform(0, 2 * np.pi, size=(n_harmonics, n))
    amp = rng.uniform(0.3, 1.0, size=(n_harmonics, n)) / n_harmonics
    return np.einsum("hn,thn->tn", amp, np.sin(2 * np.pi * freq[None] * t[:, None, None] + phase[None]))


def _check_sizes(function: str, n_frames: int, noise: float) -> None:
    if n_frames < 1:
        raise ValidationError(f"{function}: expected n_frames >= 1, got {n_frames}")
    if not (np.isfinite(noise) and noise >= 0):
        raise ValidationError(f"noise: expected a finite standard deviation >= 0, got {noise}")


def _mask(rng: np.random.Generator, shape: tuple[int, int], missing: float) -> np.ndarray | None:
    if not 0 <= missing < 1:
        raise ValidationError(f"missing: expected a fraction in [0, 1), got {missing}")
    if missing == 0:
        return None
    return (rng.random(shape) >= missing).astype(np.float64)


# --------------------------------------------------------------------------- low rank
def lowrank_sequence(n_frames: int = 100, n_points: int = 30, n_basis: int = 3, *, noise: float = 0.0,
                     missing: float = 0.0, cameras: str = "random", deformation: float = 0.4, seed: int = 0,
                     name: str | None = None) -> Sequence:
    """Shapes ``X_f = sum_k c_fk B_k`` seen by orthographic cameras.

    Args:
        n_basis: `K`; 1 gives a rigid object (c_f0 = 1).
        noise: standard deviation of Gaussian noise added to the 2D (shape
            units: the basis shapes have unit RMS size).
        missing: fraction of entries given visibility 0.
        cameras: ``"random"`` (independent uniform rotations) or ``"smooth"``
            (a rotation that turns steadily about a random axis).
        deformation: size of the non-rigid coefficients relative to the mean shape.

    Returns:
        A sequence with ``points_3d`` (camera frame, centred) and
        ``camera_rotations``; ``meta['basis']`` records `K`.
    """
    if n_frames < 1 or n_points < 3 or n_basis < 1:
        raise ValidationError(f"lowrank_sequence: expected n_frames >= 1, n_points >= 3, n_basis >= 1, got "
                              f"{n_frames}, {n_points}, {n_basis}")
    _check_sizes("lowrank_sequence", n_frames, noise)
    name = name or f"lowrank_K{n_basis}_F{n_frames}_P{n_points}_s{seed}"
    rng = rng_for(seed, name)
    basis = rng.standard_normal((n_basis, n_points, 3))  # (K, P, 3)
    basis -= basis.mean(axis=1, keepdims=True)
    basis /= np.sqrt((basis**2).sum(axis=(1, 2), keepdims=True) / n_points)
    t = np.linspace(0, 1, n_frames)
    coef = np.ones((n_frames, n_basis))
    if n_basis > 1:
        coef[:, 1:] = deformation * 2 * _smooth_signal(rng, t * 3, n_basis - 1)
    shapes = np.einsum("fk,kpi->fpi", coef, basis)  # (F, P, 3) object frame
    if cameras == "random":
        rot = random_rotations(n_frames, rng)
    elif cameras == "smooth":
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        angles = np.linspace(0, rng.uniform(0.5, 1.0) * np.pi, n_frames)
        rot = (Rotation.from_rotvec(angles[:, None] * axis) * Rotation.random(random_state=rng)).as_matrix()
    else:
        raise ValidationError(f"cameras: expected 'random' or 'smooth', got {cameras!r}")
    cam = np.einsum("fij,fpj->fpi", rot, shapes)  # (F, P, 3)
    p2 = cam[..., :2] + noise * rng.standard_normal((n_frames, n_points, 2))
    return Sequence(points_2d=p2, visibility=_mask(rng, (n_frames, n_points), missing), points_3d=cam,
                    camera_rotations=rot, name=name, meta={"dataset": "synthetic-lowrank", "basis": str(n_basis)})


# --------------------------------------------------------------------------- human
#: Rest offsets of the 17 joints from their parents, mm, body frame (x = subject's left, y = up, z = forward).
_OFFSETS = np.array([
    [0, 0, 0], [-130, 0, 0], [0, -440, 0], [0, -440, 0], [130, 0, 0], [0, -440, 0], [0, -440, 0],
    [0, 230, 10], [0, 250, 0], [0, 110, 60], [0, 110, -40], [150, -20, 0], [0, -280, 0], [0, -250, 0],
    [-150, -20, 0], [0, -280, 0], [0, -250, 0]], dtype=np.float64)
MOTIONS = ("walking", "sitting_down", "reaching", "bending", "turning", "waving")
SUBJECTS = h36m.TRAIN_SUBJECTS + h36m.TEST_SUBJECTS
_J = {n: i for i, n in enumerate(h36m.JOINT_NAMES)}


@dataclass(frozen=True)
class SyntheticCamera:
    """A synthetic camera: `rotation` (3, 3) world-to-camera, `centre` (3,) mm, `intrinsics` (3, 3)."""

    rotation: np.ndarray
    centre: np.ndarray
    intrinsics: np.ndarray

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) @ self.rotation.T


def ring_cameras(seed: int = 0, distance: float = 5000.0, height: float = 1500.0) -> list[SyntheticCamera]:
    """Four cameras around the origin at 45 + 90k degrees, looking at the subject (y up, mm)."""
    rng = rng_for(seed, "cameras")
    target = np.array([0.0, 900.0, 0.0])
    cams = []
    for k in range(4):
        az = np.deg2rad(45 + 90 * k + rng.uniform(-10, 10))
        centre = np.array([distance * np.sin(az), height + rng.uniform(-300, 300), distance * np.cos(az)])
        z = target - centre
        z /= np.linalg.norm(z)
        x = np.cross(z, [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        f = 1145.0 + rng.uniform(-5, 5)
        k_mat = np.array([[f, 0, 512.0], [0, f, 515.0], [0, 0, 1]])
        cams.append(SyntheticCamera(np.stack([x, y, z]), centre, k_mat))
    return cams


def _bone_scales(subject: str, seed: int) -> np.ndarray:
    rng = rng_for(seed, "bones", subject)
    return rng.uniform(0.88, 1.12) * rng.uniform(0.95, 1.05, size=17)


def _ramp(t: np.ndarray, duration: float) -> np.ndarray:
    """Smooth 0 -> 1 -> 0 over each period of ``duration`` seconds."""
    return 0.5 - 0.5 * np.cos(2 * np.pi * t / duration)


def _motion_angles(motion: str, t: np.ndarray, rng: np.random.Generator):
    """Joint angles `(F, 17, 3)` (rad, xyz Euler, local), root yaw `(F,)` and root position `(F, 3)` mm."""
    n = len(t)
    ang = np.zeros((n, 17, 3))
    yaw = np.full(n, rng.uniform(0, 2 * np.pi))
    root = np.zeros((n, 3))
    root[:, 1] = 900.0
    d = np.deg2rad
    speed = rng.uniform(0.8, 1.2)
    period = rng.uniform(5, 8)
    if motion == "walking":
        w = 2 * np.pi * 0.9 * speed * t
        swing = d(25) * np.sin(w)
        ang[:, _J["RHip"], 0] = -swing
        ang[:, _J["LHip"], 0] = swing
        ang[:, _J["RKnee"], 0] = d(35) * np.maximum(0, np.sin(w + 1.2)) + d(5)
        ang[:, _J["LKnee"], 0] = d(35) * np.maximum(0, np.sin(w + 1.2 + np.pi)) + d(5)
        ang[:, _J["RShoulder"], 0] = swing * 0.8
        ang[:, _J["LShoulder"], 0] = -swing * 0.8
        ang[:, _J["RElbow"], 0] = -d(20) - d(10) * np.sin(w)
        ang[:, _J["LElbow"], 0] = -d(20) + d(10) * np.sin(w)
        # walk on a circle of radius 1.5 m, heading along the tangent
        phi = yaw[0] + 1.2 * speed * t / 1.5
        root[:, 0] = 1500 * np.sin(phi)
        root[:, 2] = 1500 * np.cos(phi)
        root[:, 1] += 20 * np.sin(2 * w)
        yaw = phi + np.pi / 2
    elif motion == "sitting_down":
        s = _ramp(t, period)
        ang[:, _J["RHip"], 0] = ang[:, _J["LHip"], 0] = -d(90) * s
        ang[:, _J["RKnee"], 0] = ang[:, _J["LKnee"], 0] = d(95) * s
        ang[:, _J["Spine"], 0] = d(25) * s
        ang[:, _J["RShoulder"], 0] = ang[:, _J["LShoulder"], 0] = -d(30) * s
        ang[:, _J["RElbow"], 0] = ang[:, _J["LElbow"], 0] = -d(40) * s
        root[:, 1] -= 430 * s
        root[:, 2] -= 150 * s
    elif motion == "reaching":
        s1 = _ramp(t, period)
        s2 = _ramp(t + period / 2, period)
        ang[:, _J["RShoulder"], 0] = -d(rng.uniform(100, 150)) * s1
        ang[:, _J["LShoulder"], 0] = -d(rng.uniform(100, 150)) * s2
        ang[:, _J["RElbow"], 0] = -d(30) * (1 - s1)
        ang[:, _J["LElbow"], 0] = -d(30) * (1 - s2)
        ang[:, _J["Spine"], 0] = d(15) * np.maximum(s1, s2)
        ang[:, _J["Spine"], 1] = d(20) * (s1 - s2)
    elif motion == "bending":
        s = _ramp(t, period)
        ang[:, _J["Spine"], 0] = d(70) * s
        ang[:, _J["Thorax"], 0] = d(15) * s
        ang[:, _J["RHip"], 0] = ang[:, _J["LHip"], 0] = -d(20) * s
        ang[:, _J["RShoulder"], 0] = ang[:, _J["LShoulder"], 0] = -d(70) * s
        ang[:, _J["Head"], 0] = -d(30) * s
    elif motion == "turning":
        yaw = yaw + 2 * np.pi * t / (period * 2)
        step = d(15) * np.sin(2 * np.pi * 1.0 * t)
        ang[:, _J["RHip"], 0] = -np.maximum(step, 0)
        ang[:, _J["LHip"], 0] = np.minimum(step, 0)
        ang[:, _J["RKnee"], 0] = 2 * np.maximum(step, 0)
        ang[:, _J["LKnee"], 0] = -2 * np.minimum(step, 0)
        ang[:, _J["RShoulder"], 2] = -d(20)
        ang[:, _J["LShoulder"], 2] = d(20)
    elif motion == "waving":
        s = np.clip(2 * _ramp(t, period * 1.5), 0, 1)
        ang[:, _J["RShoulder"], 2] = -d(140) * s
        ang[:, _J["RElbow"], 2] = -(d(30) + d(30) * (1 + np.sin(2 * np.pi * 2 * t))) * s
        ang[:, _J["Head"], 1] = d(20) * np.sin(2 * np.pi * 0.3 * t)
    else:
        raise ValidationError(f"motion: expected one of {MOTIONS}, got {motion!r}")
    # individual style: smooth perturbations on every joint
    ang += d(6) * _smooth_signal(rng, t, 17 * 3, max_freq=0.6).reshape(n, 17, 3)
    return ang, yaw, root


def human_motion(subject: str, motion: str, n_frames: int = 200, fps: float = 10.0, *, seed: int = 0,
                 take: int = 0) -> np.ndarray:
    """World-frame joint positions `(F, 17, 3)` in mm (y up) of one subject performing ``motion``."""
    rng = rng_for(seed, "motion", subject, motion, take)
    t = np.arange(n_frames) / fps
    ang, yaw, root = _motion_angles(motion, t, rng)
    offsets = _OFFSETS * _bone_scales(subject, seed)[:, None]  # (17, 3)
    local = Rotation.from_euler("xyz", ang.reshape(-1, 3)).as_matrix().reshape(n_frames, 17, 3, 3)
    glob = np.empty_like(local)
    pos = np.empty((n_frames, 17, 3))
    root_rot = Rotation.from_euler("y", yaw[:, None]).as_matrix()  # (F, 3, 3)
    for j, parent in enumerate(h36m.PARENTS):  # 17 joints: a loop over the tree, vectorised over frames
        if parent < 0:
            glob[:, j] = root_rot @ local[:, j]
            pos[:, j] = root
        else:
            glob[:, j] = glob[:, parent] @ local[:, j]
            pos[:, j] = pos[:, parent] + np.einsum("fij,j->fi", glob[:, parent], offsets[j])
    return pos


def human_sequences(subjects: tuple[str, ...] = SUBJECTS, motions: tuple[str, ...] = MOTIONS,
                    cameras: tuple[int, ...] = (1, 2, 3, 4), *, n_frames: int = 200, fps: float = 10.0,
                    projection: str = "orthographic", noise: float = 0.0, missing: float = 0.0, takes: int = 1,
                    seed: int = 0) -> list[Sequence]:
    """The synthetic Human3.6M stand-in: one sequence per subject, motion, take and camera.

    Sequences are named like Human3.6M's (``S9/walking/cam1``) and carry the
    same ``meta`` keys (``subject``, ``action``, ``camera``, ``input``), the 17
    joint names and the skeleton, so benchmark code treats both alike.

    Args:
        projection: ``"orthographic"`` (2D in mm, like GT-ortho) or
            ``"perspective"`` (pixels, like GT-persp).
        noise: detector-like 2D noise, standard deviation in 2D units (px for
            perspective, mm for orthographic), heavier-tailed on wrists/feet.
        missing: fraction of 2D entries marked missing (visibility 0).
        takes: sub-actions per motion (like Human3.6M's two).
    """
    if projection not in ("orthographic", "perspective"):
        raise ValidationError(f"projection: expected 'orthographic' or 'perspective', got {projection!r}")
    _check_sizes("human_sequences", n_frames, noise)
    cams = ring_cameras(seed)
    out = []
    extremity = np.isin(np.arange(17), [_J[n] for n in ("RFoot", "LFoot", "RWrist", "LWrist", "Head")])
    for subj in subjects:
        for motion in motions:
            for take in range(takes):
                world = human_motion(subj, motion, n_frames, fps, seed=seed, take=take)
                for c in cameras:
                    cam = cams[c - 1]
                    cam3d = cam.world_to_camera(world)  # (F, 17, 3)
                    name = f"{subj}/{motion}{'' if take == 0 else f' {take}'}/cam{c}"
                    rng = rng_for(seed, "noise", name)
                    if projection == "orthographic":
                        p2, k = cam3d[..., :2].copy(), None
                    else:
                        p2, k = project_perspective(cam3d, cam.intrinsics), cam.intrinsics
                    if noise > 0:
                        scale = noise * np.where(extremity, 1.5, 1.0)[None, :, None]
                        p2 = p2 + scale * rng.standard_t(df=4, size=p2.shape) / np.sqrt(2)
                    out.append(Sequence(
                        points_2d=p2, visibility=_mask(rng, p2.shape[:2], missing), points_3d=cam3d,
                        projection=projection, intrinsics=k,
                        camera_rotations=np.broadcast_to(cam.rotation, (n_frames, 3, 3)), name=name,
                        joint_names=h36m.JOINT_NAMES, edges=np.array(h36m.EDGES), fps=fps,
                        meta={"dataset": "synthetic-human", "subject": subj, "action": motion,
                              "subaction": f"{motion} {take}", "camera": str(c),
                              "input": "gt-ortho" if projection == "orthographic" else "gt-persp"}))
    return out


# --------------------------------------------------------------------------- faces
def _face_template() -> np.ndarray:
    """`(68, 3)` mean face in the iBUG 68-landmark order (mm, x right, y up, z towards the viewer)."""
    pts = []
    phi = np.linspace(-np.pi / 2 - 0.25, np.pi / 2 + 0.25, 17)  # jaw 0-16, from the face's right
    pts += [[-72 * np.sin(-p), 5 - 68 * np.cos(p) * 1.05 - 10 * (np.abs(p) < 1), 45 * np.cos(p) - 35] for p in phi]
    for side in (-1, 1):  # brows 17-21 (right), 22-26 (left)
        xs = np.linspace(-55, -15, 5) if side < 0 else np.linspace(15, 55, 5)
        pts += [[x, 38 + 6 * np.sin(np.pi * (abs(x) - 15) / 40), 22 - 0.008 * x * x] for x in xs]
    pts += [[0, y, z] for y, z in zip(np.linspace(28, 2, 4), np.linspace(22, 42, 4))]  # nose bridge 27-30
    pts += [[x, -10 + 0.04 * x * x, 30 - 0.3 * abs(x)] for x in np.linspace(-15, 15, 5)]  # nose base 31-35
    for cx in (-32, 32):  # eyes 36-41, 42-47
        a = np.array([np.pi, 2 * np.pi / 3, np.pi / 3, 0, -np.pi / 3, -2 * np.pi / 3])
        if cx > 0:
            a = np.array([np.pi, 2 * np.pi / 3, np.pi / 3, 0, -np.pi / 3, -2 * np.pi / 3])
        pts += [[cx + 13 * np.cos(ai), 22 + 5 * np.sin(ai), 14 - 3 * np.cos(ai) ** 2] for ai in a]
    a = np.pi - np.linspace(0, 2 * np.pi, 12, endpoint=False)  # outer lips 48-59
    pts += [[25 * np.cos(ai), -38 + 10 * np.sin(ai), 24 - 8 * np.cos(ai) ** 2] for ai in a]
    a = np.pi - np.linspace(0, 2 * np.pi, 8, endpoint=False)  # inner lips 60-67
    pts += [[16 * np.cos(ai), -38 + 4 * np.sin(ai), 25 - 6 * np.cos(ai) ** 2] for ai in a]
    x = np.array(pts, dtype=np.float64)
    assert x.shape == (68, 3)
    return x


FACE_EDGES = tuple([(i, i + 1) for i in range(16)] + [(i, i + 1) for i in range(17, 21)]
                   + [(i, i + 1) for i in range(22, 26)] + [(i, i + 1) for i in range(27, 35)]
                   + [(36 + i, 36 + (i + 1) % 6) for i in range(6)] + [(42 + i, 42 + (i + 1) % 6) for i in range(6)]
                   + [(48 + i, 48 + (i + 1) % 12) for i in range(12)] + [(60 + i, 60 + (i + 1) % 8) for i in range(8)])


def face_sequences(n_sequences: int = 8, n_frames: int = 300, *, noise: float = 0.0, missing: float = 0.0,
                   seed: int = 0) -> list[Sequence]:
    """68-landmark faces: identity (per sequence), expression and head rotation (per frame).

    2D is the orthographic projection of the camera-frame landmarks (mm).
    """
    _check_sizes("face_sequences", n_frames, noise)
    template = _face_template()
    lower = template[:, 1] < -25  # jaw, lower lip region
    mouth = np.arange(68) >= 48
    brows = (np.arange(68) >= 17) & (np.arange(68) < 27)
    out = []
    for s in range(n_sequences):
        name = f"face{s:03d}"
        rng = rng_for(seed, "face", name)
        ident = template * rng.uniform(0.9, 1.1, size=3)  # width, height, depth
        ident = ident + 3.0 * _smooth_field(rng, template)
        t = np.arange(n_frames) / 30.0
        e = np.clip(0.5 + _smooth_signal(rng, t, 3, max_freq=0.5), 0, 1)  # open, smile, brows
        shapes = np.repeat(ident[None], n_frames, axis=0)
        open_disp = np.where(lower, -(template[:, 1].max() - template[:, 1]) / 8, 0.0)  # (68,)
        shapes[:, :, 1] += e[:, :1] * open_disp[None] * lower
        smile = mouth * np.abs(template[:, 0]) / 25.0
        shapes[:, :, 0] += 4 * e[:, 1:2] * smile * np.sign(template[:, 0])
        shapes[:, :, 1] += 4 * e[:, 1:2] * smile
        shapes[:, :, 1] += 5 * e[:, 2:3] * brows
        angles = np.deg2rad([40, 20, 10]) * _smooth_signal(rng, t, 3, max_freq=0.3) * 1.5  # yaw, pitch, roll
        rot = Rotation.from_euler("yxz", angles).as_matrix()  # (F, 3, 3)
        cam = np.einsum("fij,fpj->fpi", rot, shapes)
        cam -= cam.mean(axis=1, keepdims=True)
        p2 = cam[..., :2] + noise * rng.standard_normal((n_frames, 68, 2))
        out.append(Sequence(points_2d=p2, visibility=_mask(rng, (n_frames, 68), missing), points_3d=cam,
                            camera_rotations=rot, name=name, edges=np.array(FACE_EDGES), fps=30.0,
                            meta={"dataset": "synthetic-face"}))
    return out


def _smooth_field(rng: np.random.Generator, points: np.ndarray, n_waves: int = 6) -> np.ndarray:
    """`(N, 3)` smooth random displacement field evaluated at ``points`` `(N, 3)`."""
    k = rng.standard_normal((n_waves, 3)) / 60.0
    ph = rng.uniform(0, 2 * np.pi, n_waves)
    amp = rng.standard_normal((n_waves, 3)) / np.sqrt(n_waves)
    return np.sin(points @ k.T + ph) @ amp


# --------------------------------------------------------------------------- dense surfaces
def surface_sequence(n_frames: int = 120, n_u: int = 60, n_v: int = 50, *, noise: float = 0.0, seed: int = 0,
                     name: str | None = None) -> Sequence:
    """A dense deforming tube (torso-like surface, ``n_u * n_v`` points) turning about the vertical axis.

    The tube breathes, bends and twists smoothly; each frame is seen by an
    orthographic camera rotated randomly about the y axis (as PRN does for
    SURREAL). Units: mm.
    """
    _check_sizes("surface_sequence", n_frames, noise)
    if n_u < 3 or n_v < 2:
        raise ValidationError(f"surface_sequence: expected n_u >= 3, n_v >= 2, got {n_u}, {n_v}")
    name = name or f"surface_{n_u}x{n_v}_F{n_frames}_s{seed}"
    rng = rng_for(seed, "surface", name)
    u = np.linspace(0, 2 * np.pi, n_u, endpoint=False)
    v = np.linspace(0, 1, n_v)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    uu, vv = uu.ravel(), vv.ravel()  # (P,)
    t = np.arange(n_frames) / 10.0
    a = _smooth_signal(rng, t, 4, max_freq=0.4)  # (F, 4)
    radius = 150 * (1 + 0.15 * a[:, :1] * np.sin(2 * uu + 1.0)[None] * vv[None]
                    + 0.1 * a[:, 1:2] * np.cos(3 * np.pi * vv)[None])
    twist = 0.6 * a[:, 2:3] * vv[None]
    x = radius * np.cos(uu[None] + twist) * 1.3
    z = radius * np.sin(uu[None] + twist)
    y = 600 * vv[None] * np.ones_like(x)
    x = x + 250 * a[:, 3:4] * vv[None] ** 2  # bending
    shapes = np.stack([x, y, z], axis=-1)  # (F, P, 3)
    yaw = rng.uniform(-np.pi, np.pi, n_frames)
    rot = Rotation.from_euler("y", yaw[:, None]).as_matrix()
    cam = np.einsum("fij,fpj->fpi", rot, shapes)
    cam -= cam.mean(axis=1, keepdims=True)
    p2 = cam[..., :2] + noise * rng.standard_normal(cam[..., :2].shape)
    return Sequence(points_2d=p2, points_3d=cam, camera_rotations=rot, name=name, fps=10.0,
                    meta={"dataset": "synthetic-surface"})


def drop_entries(seq: Sequence, fraction: float) -> Sequence:
    """``seq`` with about ``fraction`` of its `(F, P)` entries marked missing (visibility 0), uniformly at random,
    seeded by the sequence name and the fraction (the same entries in every process and run)."""
    if fraction <= 0:
        return seq
    rng = np.random.default_rng(zlib.crc32(f"missing-{seq.name}-{fraction}".encode()))
    vis = seq.weights.copy()
    vis[rng.random(vis.shape) < fraction] = 0.0
    return seq.replace(visibility=vis)


def orbit_sequence(world: np.ndarray, turn_deg: float, *, up: int = 1, elevation_deg: float = 15.0,
                   start_deg: float = 0.0, name: str = "orbit", **sequence_fields) -> Sequence:
    """World-frame points ``world`` `(F, P, 3)` seen by an orthographic camera that turns steadily about the
    vertical axis (``up``: 1 for y up, 2 for z up, as Human3.6M's world) from ``start_deg`` by ``turn_deg``
    over the sequence, looking ``elevation_deg`` down at the subject.

    Returns:
        A :class:`Sequence` with ``points_3d`` `(F, P, 3)` in the camera frame (about the centroid of the
        whole motion, so the subject's own displacement stays in the 2D), ``camera_rotations`` `(F, 3, 3)`
        (world to camera) and ``sequence_fields`` (``joint_names``, ``edges``, ``meta``, ...).
    """
    world = np.asarray(world, dtype=np.float64)
    if world.ndim != 3 or world.shape[2] != 3:
        raise ValidationError(f"world: expected (F, P, 3) points, got shape {world.shape}")
    if up not in (1, 2):
        raise ValidationError(f"up: expected 1 (y up) or 2 (z up), got {up!r}")
    n_frames = world.shape[0]
    # a camera frame (x right, y up, z towards the viewer) of a y-up world, for a z-up one first turned to y up
    to_y_up = np.eye(3) if up == 1 else np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    yaw = np.deg2rad(start_deg + turn_deg * np.linspace(0.0, 1.0, n_frames))
    rot = (Rotation.from_euler("x", -elevation_deg, degrees=True) * Rotation.from_euler("y", yaw[:, None])).as_matrix()
    rot = rot @ to_y_up  # (F, 3, 3)
    cam = np.einsum("fij,fpj->fpi", rot, world - world.reshape(-1, 3).mean(axis=0))  # (F, P, 3)
    return Sequence(points_2d=cam[..., :2].copy(), points_3d=cam, camera_rotations=rot, name=name,
                    **sequence_fields)
