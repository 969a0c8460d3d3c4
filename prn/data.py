"""Training data for PRN: per-frame normalisation and group sampling.

Normalisation (official code): per frame, subtract the mean over the
(visible) points and divide by the Frobenius norm of the centred xy. The 3D
targets of evaluation get the same treatment with the ground truth's own xy
norm, and predictions are scaled back by it (:func:`denormalize`). A frame
with missing points is centred on its visible points and divided by their
norm times ``sqrt(P / visible)``, so that its size does not depend on how
many points are missing (with every point visible this is the paper's norm);
its prediction is scaled back by the ground truth's same statistic over the
same points (``denormalize(..., visibility)``).

Group sampling (one PR-loss group = ``group_size`` frames):

- ``"multiview"`` (Human3.6M): from one long sequence (a subject's
  sub-action take, all actions concatenated), a random start, frames
  ``gap`` apart, the camera cycling 1, 2, 3, 4, 1, ... so that one group sees
  viewpoint variation;
- ``"random"`` (300-VW): frames drawn at random across all sequences;
- ``"consecutive"`` (SURREAL): consecutive frames of one sequence.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from nrsfm.errors import ValidationError
from nrsfm.sequence import Sequence

SAMPLINGS = ("multiview", "random", "consecutive")


def normalize_2d(points_2d: np.ndarray, visibility: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centre each frame on its visible points and divide by their xy Frobenius norm times
    ``sqrt(P / visible)`` (the norm itself when every point is visible).

    Args:
        points_2d: `(F, P, 2)`; visibility: `(F, P)` or None.

    Returns:
        `(F, P, 2)` normalised points (missing points set to 0) and `(F,)` scales.
    """
    w = np.ones(points_2d.shape[:2]) if visibility is None else (visibility > 0).astype(np.float64)
    cnt = np.maximum(w.sum(axis=1, keepdims=True), 1.0)[..., None]  # (F, 1, 1)
    centre = (np.nan_to_num(points_2d) * w[..., None]).sum(axis=1, keepdims=True) / cnt
    c = np.nan_to_num(points_2d - centre) * w[..., None]
    scale = np.linalg.norm(c.reshape(len(c), -1), axis=1) * np.sqrt(points_2d.shape[1] / cnt[:, 0, 0])
    scale = np.where(scale > 0, scale, 1.0)
    return c / scale[:, None, None], scale


def unit_frames(seq):
    """A :class:`~nrsfm.sequence.Sequence` with each frame's 2D centred on its visible points and divided by their
    xy norm (:func:`normalize_2d`, PRN's input normalisation). Weak-perspective tracks (GT-persp, SH) change scale
    with each frame's depth and camera, which an orthographic NRSfM solver reads as deformation; a pseudo-label is
    normalised per frame before a network learns it, so solving such frames loses nothing."""
    import dataclasses

    return dataclasses.replace(seq, points_2d=normalize_2d(seq.points_2d, seq.visibility)[0])


def normalize_3d(points_3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre `(F, P, 3)` shapes on the joints' mean; divide by the xy Frobenius norm. Returns (shapes, scales)."""
    c = points_3d - points_3d.mean(axis=1, keepdims=True)
    scale = np.linalg.norm(c[..., :2].reshape(len(c), -1), axis=1)
    scale = np.where(scale > 0, scale, 1.0)
    return c / scale[:, None, None], scale


def denormalize(pred: np.ndarray, gt_3d: np.ndarray, visibility: np.ndarray | None = None) -> np.ndarray:
    """Scale normalised predictions `(F, P, 3)` back to the ground truth's units by its xy norm (PRN protocol).

    With ``visibility`` `(F, P)` (the points a test input was normalised on), by the ground truth's xy statistic
    over those points, as :func:`normalize_2d` computes it."""
    if visibility is None:
        _, scale = normalize_3d(gt_3d)
    else:
        _, scale = normalize_2d(gt_3d[..., :2], visibility)
    return pred * scale[:, None, None]


#: Name prefixes of a left / right pair of joints (``LHip`` / ``RHip``, ``leftShoulder`` / ``rightShoulder``).
_SIDES = (("Left", "Right"), ("left", "right"), ("L", "R"), ("l_", "r_"))


def _side(name: str) -> tuple[str, str, str] | None:
    """(prefix, partner prefix, rest) where ``name`` names one side of the body, else None."""
    for a, b in _SIDES:
        for this, other in ((a, b), (b, a)):
            rest = name[len(this):]
            if name.startswith(this) and rest and (len(this) > 1 or rest[0].isupper() or rest[0] in "_ ."):
                return this, other, rest
    return None


def mirror_permutation(joint_names) -> np.ndarray | None:
    """`(P,)` the index of each joint's mirror image (left <-> right; a joint on the midline is its own), read from
    the names' side prefixes (``LHip`` / ``RHip``, ``leftKnee`` / ``rightKnee``, ``l_ankle`` / ``r_ankle``); None
    without names, without any left / right pair, or where a named side has no partner."""
    if not joint_names:
        return None
    names = list(joint_names)
    perm = np.arange(len(names))
    for i, n in enumerate(names):
        side = _side(n)
        if side is not None:
            partner = side[1] + side[2]
            if partner not in names:
                return None
            perm[i] = names.index(partner)
    return perm if (perm != np.arange(len(names))).any() else None


def mirror_perms(joint_names, input_points: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(input, output) mirror permutations (:func:`mirror_permutation`) for a network whose inputs are
    ``input_points`` of the joints (None: all), or None where the names pair no joints or an input's mirror
    partner is no input."""
    perm = mirror_permutation(joint_names)
    if perm is None:
        return None
    keep = np.arange(len(perm)) if input_points is None else np.asarray(input_points)
    pos = {int(k): i for i, k in enumerate(keep)}
    if any(int(perm[k]) not in pos for k in keep):
        return None
    return np.array([pos[int(perm[k])] for k in keep]), perm


def mirror_points(points: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """`(..., P, D)` points reflected in the image's x axis: each joint takes its mirror partner's point
    (``perm``, :func:`mirror_permutation`) with x negated. Its own inverse."""
    out = np.array(points, dtype=np.float64)[..., perm, :]
    out[..., 0] *= -1.0
    return out


def mirror_sequence(seq: Sequence, perm: np.ndarray) -> Sequence:
    """The sequence's mirror image (:func:`mirror_points` on the 2D and 3D; visibility follows the joints), a new
    take (``meta['subject']`` and the name marked ``mirrored``), so that PRN's groups never mix the two."""
    import dataclasses

    if seq.projection != "orthographic" and seq.intrinsics is not None:
        seq = seq.to_weak_perspective()
    meta = dict(seq.meta)
    meta["subject"] = f"{meta.get('subject', seq.name)} mirrored"
    return dataclasses.replace(
        seq, points_2d=mirror_points(seq.points_2d, perm),
        visibility=None if seq.visibility is None else seq.visibility[:, perm],
        points_3d=None if seq.points_3d is None else mirror_points(seq.points_3d, perm),
        camera_rotations=None, name=f"{seq.name} mirrored", meta=meta)


@dataclass
class TrainingSet:
    """Frames ready for training, with the index tables used by the group samplers.

    Attributes:
        inputs: `(N, P_in, 2)` normalised network inputs; input_weights `(N, P_in)`.
        targets: `(N, P, 2)` normalised 2D compared with the predicted xy;
            target_weights `(N, P)` (0 = missing, in the data term).
        streams: for ``multiview``, `(C, T)` flat frame indices per long
            sequence (C cameras); for the other samplings, `(1, T)` per sequence.
        sampling: one of :data:`SAMPLINGS`.
        description: what was loaded (for run metadata).
        images: for PRN-CNN, one image per frame (:mod:`prn.images`), else None.
    """

    inputs: np.ndarray
    input_weights: np.ndarray
    targets: np.ndarray
    target_weights: np.ndarray
    streams: list[np.ndarray]
    sampling: str
    description: dict = field(default_factory=dict)
    input_points: np.ndarray | None = None  # indices of the input points kept (e.g. 16 of 17 for SH)
    images: object = None  # PRN-CNN: an image source, (N, H, W, 3) uint8, one image per frame (prn.images)

    def prepare_inputs(self, seq: Sequence, normalise_on: str = "visible") -> tuple[np.ndarray, np.ndarray]:
        """Normalised `(F, P_in, 2)` inputs and `(F, P_in)` weights of a test sequence.

        ``normalise_on="visible"``: each frame centred and scaled on its visible points, as the training set's
        frames are. ``"all"``: centred and scaled on all its points, the missing ones included, which are then set
        to 0, as a network trained with ``missing_points`` sees its inputs (the points it drops were normalised
        with the rest); this reads the 2D of the missing points, so it applies where they were dropped on purpose
        (supplementary Table S1), not to points that were never observed.
        """
        if normalise_on not in ("visible", "all"):
            raise ValidationError(f"normalise_on: expected 'visible' or 'all', got {normalise_on!r}")
        if normalise_on == "all":
            x = normalize_2d(seq.points_2d)[0] * (seq.weights > 0)[..., None]
        else:
            x, _ = normalize_2d(seq.points_2d, seq.visibility)
        keep = np.arange(seq.n_points) if self.input_points is None else self.input_points
        return x[:, keep], seq.weights[:, keep]

    @property
    def n_points(self) -> int:
        return self.targets.shape[1]

    @property
    def n_inputs(self) -> int:
        return self.inputs.shape[1]

    def sample_groups(self, rng: np.random.Generator, n_groups: int, group_size: int, gap: int = 5) -> np.ndarray:
        """`(n_groups * group_size,)` flat frame indices, group-major."""
        out = []
        for _ in range(n_groups):
            if self.sampling == "random":
                if group_size > len(self.inputs):
                    raise ValidationError(f"group sampling: expected at least {group_size} training frames for a "
                                          f"group, got {len(self.inputs)}; lower group_size")
                out.append(rng.choice(len(self.inputs), size=group_size, replace=False))
                continue
            step = gap if self.sampling == "multiview" else 1
            span = step * (group_size - 1) + 1
            ok = [s for s in self.streams if s.shape[1] >= span]
            if not ok:
                raise ValidationError(f"group sampling: no sequence has {span} frames for {group_size} frames "
                                      f"{step} apart; lower group_size or gap")
            s = ok[rng.integers(len(ok))]
            t0 = rng.integers(s.shape[1] - span + 1)
            t = t0 + step * np.arange(group_size)
            cams = (rng.integers(s.shape[0]) + np.arange(group_size)) % s.shape[0]
            out.append(s[cams, t])
        return np.concatenate(out)


def _take_key(seq: Sequence) -> tuple[str, int]:
    """(subject, take): the plain action file is take 0, a numbered one (``'Walking 1'``) take 1."""
    sub = seq.meta.get("subaction", seq.meta.get("action", ""))
    return seq.meta.get("subject", seq.name), 0 if " " not in sub.strip() or sub.strip().endswith(" 0") else 1


def build_training_set(inputs: list[Sequence], targets: list[Sequence] | None = None, *,
                       sampling: str = "multiview", drop_invisible_inputs: bool = True,
                       images: list | None = None, scores: bool = False) -> TrainingSet:
    """Stack sequences into a :class:`TrainingSet`.

    Args:
        inputs: the network's 2D inputs (e.g. Stacked Hourglass detections).
        targets: the 2D compared with the prediction by the data term, frame
            for frame (default: the inputs). The paper's SH networks read
            detections and are trained against ground-truth 2D.
        sampling: see :data:`SAMPLINGS`. ``multiview`` groups sequences by
            ``meta['subject']`` and sub-action take, concatenating actions,
            with one stream row per ``meta['camera']``.
        drop_invisible_inputs: drop input points never visible in any frame
            (Neck/Nose for Stacked Hourglass: 16 inputs, 17 outputs).
        images: for PRN-CNN, one image source per input sequence (`(F, H, W, 3)` uint8 arrays or lazy
            sources, :mod:`prn.images`), frame for frame.
        scores: the data term weighs each target point by the input's visibility there, read as a detection
            score in [0, 1] (PRN-FCN-W); points that are no input keep their target weight.
    """
    if sampling not in SAMPLINGS:
        raise ValidationError(f"sampling: expected one of {SAMPLINGS}, got {sampling!r}")
    targets = inputs if targets is None else targets
    if len(targets) != len(inputs) or not inputs:
        raise ValidationError(f"targets: expected one target sequence per input ({len(inputs)}), got {len(targets)}")
    if images is not None:
        if len(images) != len(inputs):
            raise ValidationError(f"images: expected one image source per input sequence ({len(inputs)}), got "
                                  f"{len(images)}")
        for seq, im in zip(inputs, images):
            if len(im) != seq.n_frames:
                raise ValidationError(f"{seq.name}: {seq.n_frames} frames but {len(im)} images")
    keep = np.ones(inputs[0].n_points, bool)
    if drop_invisible_inputs:
        keep = np.any([(s.weights > 0).any(axis=0) for s in inputs], axis=0)
    xs, xw, ys, yw = [], [], [], []
    offsets, start = [], 0
    for si, ti in zip(inputs, targets):
        if si.n_frames != ti.n_frames:
            raise ValidationError(f"{si.name}: input has {si.n_frames} frames, target {ti.n_frames}")
        x, _ = normalize_2d(si.points_2d, si.visibility)
        y, _ = normalize_2d(ti.points_2d, ti.visibility)
        xs.append(x[:, keep])
        xw.append(si.weights[:, keep])
        ys.append(y)
        yw.append(ti.weights * np.where(keep, si.weights, 1.0) if scores else ti.weights)
        offsets.append(start)
        start += si.n_frames
    streams: list[np.ndarray] = []
    if sampling == "multiview":
        # (subject, take) -> camera -> list of (action, flat indices)
        table: dict = defaultdict(lambda: defaultdict(list))
        for seq, off in zip(inputs, offsets):
            table[_take_key(seq)][seq.meta.get("camera", "1")].append(
                (seq.meta.get("action", seq.name), np.arange(off, off + seq.n_frames)))
        for key in sorted(table):
            cams = table[key]
            rows = [np.concatenate([idx for _, idx in sorted(cams[c], key=lambda a: a[0])]) for c in sorted(cams)]
            t = min(len(r) for r in rows)
            streams.append(np.stack([r[:t] for r in rows]))
    else:
        streams = [np.arange(off, off + s.n_frames)[None] for s, off in zip(inputs, offsets)]
    return TrainingSet(inputs=np.concatenate(xs), input_weights=np.concatenate(xw), targets=np.concatenate(ys),
                       target_weights=np.concatenate(yw), streams=streams, sampling=sampling,
                       description={"sequences": len(inputs), "frames": int(start), "streams": len(streams),
                                    "inputs": int(keep.sum()), "outputs": int(targets[0].n_points)},
                       input_points=np.flatnonzero(keep),
                       images=None if images is None else _stack_images(images))


def _stack_images(sources: list):
    from prn.images import stack_images

    return stack_images(sources)
