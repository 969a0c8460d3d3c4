"""PRN paper, Table 2: MPJPE (mm) of 3D human pose from RGB images, Human3.6M.

    python -m benchmarks.table2 [--data synthetic|h36m] [--root DIR] [--quick] [--iterations N]
                                [--methods NAME,NAME] [--backbone resnet50|resnet18|small] [--image-size PX]
                                [--out DIR] [--resume | --retrain] [--plots]

Rows: PRN w/o reg, CSF2 + CNN, SPM + CNN, PRN-CNN, GT 3D, all with one network: a ResNet backbone (ImageNet
weights when they are in torch's local cache, else random initialisation; the output states which) feeding
PRN-FCN's head (:class:`prn.model.PRNCNN`). The +CNN rows train it on pseudo-3D labels that CSF2 or SPM computed
from the training sequences' 2D joints (:mod:`baselines.labels`); the data term of the PRN rows compares the
predicted xy with those 2D joints. 120,000 iterations as the paper's supplementary material.

Real data: the Human3.6M poses (train S1, S5-S8, test S9, S11 where present) and the frames of the videos
extracted as :mod:`nrsfm.datasets.frames` documents (``<root>/h36m/images/...``), cropped with the ground-truth
bounding box and resized to 224 px (ResNet-50's 7 x 7 features, as the paper); the 2D of the data term is the
perspective projection of the joints (pixels). Sequences without frames are left out, with a count.

Without data: the embedded stand-in, the synthetic humans of Table 1 (:mod:`benchmarks.table1`, GT-ortho)
rendered as shaded capsules with the left limbs red and the right blue (:mod:`nrsfm.datasets.render`), 64 px,
with a small four-layer CNN in place of the ResNet so that it trains on a CPU (``--backbone`` changes it).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

from benchmarks.harness import TableSpec, main as harness_main
from benchmarks.registry import Split
from nrsfm.errors import ValidationError
from nrsfm.metrics import mpjpe_prn_per_frame

log = logging.getLogger(__name__)

PAPER = {"PRN w/o reg": 164.5, "CSF2 + CNN": 130.6, "SPM + CNN": 114.4, "PRN-CNN": 108.9, "GT 3D": 98.8}


def rendered(seqs: list, size: int, cache: Path) -> list[np.ndarray]:
    """`(F, size, size, 3)` renders of each sequence (:func:`nrsfm.datasets.render.render_sequence`), cached in
    ``cache`` (one ``.npy`` per sequence, keyed by its name, size and a hash of its 3D points)."""
    import hashlib

    from nrsfm.datasets.render import render_sequence

    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for s in seqs:
        h = hashlib.sha1(np.ascontiguousarray(s.points_3d, np.float64).tobytes()).hexdigest()[:12]
        path = cache / f"{s.name.replace('/', '_')}-{size}-{h}.npy"
        if path.exists():
            out.append(np.load(path))
            continue
        im = render_sequence(s, size=size)
        tmp = path.with_suffix(".tmp.npy")
        np.save(tmp, im)
        tmp.replace(path)
        out.append(im)
    return out


def load(args: argparse.Namespace) -> tuple[Split, dict]:
    from benchmarks.table1 import load_splits

    args.stride = getattr(args, "stride", "auto")
    size = args.image_size or (64 if args.data == "synthetic" else 224)
    if args.data == "synthetic":
        splits, desc = load_splits(args, ("gt-ortho",))
        s = splits["gt-ortho"]
        cache = Path(args.out or "runs/table2-synthetic") / "images"
        desc.update(images=f"rendered capsules, {size} px", image_size=size)
        return Split(s.train_inputs, s.train_targets, s.test_inputs, s.test_truth, "rgb", sampling=s.sampling,
                     tag=f"{s.tag}-rgb{size}", labels_tag=s.tag, train_images=rendered(s.train_inputs, size, cache),
                     test_images=rendered(s.test_inputs, size, cache)), desc
    from nrsfm.datasets import find_dataset
    from nrsfm.datasets.frames import h36m_frames
    from nrsfm.datasets.h36m import load_cameras
    from nrsfm.errors import DataFormatError

    splits, desc = load_splits(args, ("gt-persp",))
    s = splits["gt-persp"]
    root = find_dataset("h36m", args.root)
    cams = load_cameras(root / "cameras.h5")
    stride = 5 if desc["stride"] == 1 else desc["stride"]  # video frames per pose: a 10 fps copy is every 5th

    def with_frames(seqs):
        keep, images, missing = [], [], []
        for q in seqs:
            try:
                images.append(h36m_frames(root, q, stride=stride, size=size, cameras=cams))
                keep.append(q)
            except DataFormatError as exc:
                missing.append(str(exc))
        return keep, images, missing

    tr, tr_im, tr_miss = with_frames(s.train_inputs)
    te, te_im, te_miss = with_frames(s.test_inputs)
    if not tr or not te:
        first = (tr_miss or te_miss or ["-"])[0]
        raise ValidationError(f"Table 2 needs the Human3.6M video frames under {root / 'images'} (layout in "
                              f"nrsfm.datasets.frames); {len(tr)} training and {len(te)} test sequences have them. "
                              f"First missing: {first}")
    desc.update(images=f"video frames, {size} px crops", image_size=size, sequences_without_frames=len(tr_miss)
                + len(te_miss))
    return Split(tr, tr, te, te, "rgb", sampling=s.sampling, tag=f"{s.tag}-rgb{size}-{len(tr)}", labels_tag=s.tag,
                 train_images=tr_im, test_images=te_im), desc


def _mpjpe(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return mpjpe_prn_per_frame(pred, truth)


SPEC = TableSpec(name="table2", title="Table 2 (Human3.6M, RGB images)", rows=tuple(PAPER), paper=PAPER, load=load,
                 iterations=(120_000, 3000, 400), metric="MPJPE (mm)", error=_mpjpe, real_name="h36m",
                 real_data=(("h36m", ("h36m", "h36m/images")),),
                 frame="mean-centred, z sign per frame, no Procrustes (PRN protocol); test S9",
                 context={"network": "resnet50"}, synthetic_context={"network": "small"}, images=True)


def main(argv: list[str] | None = None) -> int:
    return harness_main(SPEC, argv)


if __name__ == "__main__":
    sys.exit(main())
