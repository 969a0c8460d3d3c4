"""PRN supplementary Table 2: normalised error (NE) of 3D faces from RGB images, 300-VW (68 landmarks).

    python -m benchmarks.table_s2 [--data synthetic|300vw] [--root DIR] [--quick] [--iterations N]
                                  [--methods NAME,NAME] [--backbone resnet50|resnet18|small] [--image-size PX]
                                  [--out DIR] [--resume | --retrain] [--plots]

Rows: CSF2 + CNN, PR + CNN, PRN-CNN, one network (:class:`prn.model.PRNCNN`, as :mod:`benchmarks.table2`). The
data and split are Table 3's (:mod:`benchmarks.table3`: 32 training and 32 test videos, random cross-video
minibatches); the network reads the video frames, cropped on a square centred on the mean of the landmarks and
resized (:func:`nrsfm.datasets.frames.vw300_frames`; frames extracted to ``<root>/300vw/NNN/frames/``), and
the PRN rows' data term compares the predicted xy with the 3D landmarks' xy. 100,000 iterations as the paper.

Without data: Table 3's synthetic faces rendered as shaded contours (:mod:`nrsfm.datasets.render`), 64 px, with
the small CNN of :mod:`prn.images`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.harness import TableSpec, main as harness_main, normalized_error
from benchmarks.table3 import FACE_GROUPS
from benchmarks.registry import Split
from nrsfm.errors import ValidationError

PAPER = {"CSF2 + CNN": 0.4331, "PR + CNN": 0.4224, "PRN-CNN": 0.3092}


def load(args: argparse.Namespace) -> tuple[Split, dict]:
    from benchmarks import table3
    from benchmarks.table2 import rendered

    size = args.image_size or (64 if args.data == "synthetic" else 224)
    s, desc = table3.load(args)
    if args.data == "synthetic":
        cache = Path(args.out or "runs/table_s2-synthetic") / "images"
        desc.update(images=f"rendered contours, {size} px", image_size=size)
        return Split(s.train_inputs, s.train_targets, s.test_inputs, s.test_truth, "rgb", sampling=s.sampling,
                     tag=f"{s.tag}-rgb{size}", labels_tag=s.tag, train_images=rendered(s.train_inputs, size, cache),
                     test_images=rendered(s.test_inputs, size, cache)), desc
    from nrsfm.datasets.frames import vw300_frames

    root = args.root
    try:
        tr_im = [vw300_frames(root, q.meta["video"], q, size=size) for q in s.train_inputs]
        te_im = [vw300_frames(root, q.meta["video"], q, size=size) for q in s.test_inputs]
    except (OSError, ValueError) as exc:
        raise ValidationError(f"Table S2 needs the frames of every 300-VW video of the split (layout in "
                              f"nrsfm.datasets.frames): {exc}") from None
    desc.update(images=f"video frames, {size} px crops", image_size=size)
    return Split(s.train_inputs, s.train_targets, s.test_inputs, s.test_truth, "rgb", sampling=s.sampling,
                 tag=f"{s.tag}-rgb{size}", labels_tag=s.tag, train_images=tr_im, test_images=te_im), desc


SPEC = TableSpec(name="table_s2", title="Table S2 (300-VW faces, RGB images)", rows=tuple(PAPER), paper=PAPER,
                 load=load, iterations=(100_000, 3000, 400), metric="NE", error=normalized_error, real_name="300vw",
                 real_data=(("300vw", ("300vw-3d", "300vw")),),
                 frame="centred per frame, z sign per frame, scaled back by the ground truth's xy norm",
                 context={"network": "resnet50", **FACE_GROUPS}, synthetic_context={"network": "small", **FACE_GROUPS},
                 images=True)


def main(argv: list[str] | None = None) -> int:
    return harness_main(SPEC, argv)


if __name__ == "__main__":
    sys.exit(main())
