"""PRN paper, Table 3: normalised error (NE) of 3D faces from 2D landmarks, 300-VW (68 landmarks).

    python -m benchmarks.table3 [--data synthetic|300vw] [--root DIR] [--quick] [--iterations N]
                                [--methods NAME,NAME] [--out DIR] [--resume | --retrain]

Real data: the 3D landmarks of the 300-VW videos (:mod:`nrsfm.datasets.faces`), split into 32 training and 32
test videos (:func:`~nrsfm.datasets.faces.split_300vw`); the 2D input is their xy. Training minibatches draw
frames at random across the training videos (``sampling="random"``); 14,000 iterations as the paper. The "+NN"
rows solve each training video (cut as :func:`baselines.labels.multiview_cuts` cuts one-camera recordings) with
CSF2 or PR. NE per frame (:func:`benchmarks.harness.normalized_error`), frame-weighted over the test videos.

Without data: the embedded stand-in, synthetic 68-landmark faces (identity, expression and head rotation;
:func:`nrsfm.datasets.synthetic.face_sequences`), half for training and half for test.
"""

from __future__ import annotations

import argparse
import sys

from benchmarks.harness import TableSpec, main as harness_main, normalized_error
from benchmarks.registry import Split

PAPER = {"PRN w/o reg": 0.5201, "CSF2 + NN": 0.2751, "PR + NN": 0.2730, "C3DPO": 0.1715, "PRN-FCN": 0.1512,
         "GT 3D": 0.0441}


def load(args: argparse.Namespace) -> tuple[Split, dict]:
    if args.data == "synthetic":
        from nrsfm.datasets.synthetic import face_sequences

        n, frames = (4, 100) if args.quick else (12, 300)
        seqs = face_sequences(2 * n, frames, seed=args.seed)
        train, test = seqs[:n], seqs[n:]
        desc = {"data": "synthetic faces", "train_sequences": n, "test_sequences": n, "frames": frames}
        return Split(train, train, test, test, "gt-ortho", sampling="random",
                     tag=f"faces-{n}-{frames}-{args.seed}"), desc
    from nrsfm.datasets.faces import list_300vw, load_300vw, split_300vw

    train_v, test_v = split_300vw(list_300vw(args.root))
    if not train_v or not test_v:
        raise FileNotFoundError("300vw-3d: expected at least two videos with 3D landmarks")
    train = [load_300vw(v, args.root) for v in train_v]
    test = [load_300vw(v, args.root) for v in test_v]
    desc = {"data": "300vw", "train_videos": train_v, "test_videos": test_v}
    return Split(train, train, test, test, "gt-ortho", sampling="random",
                 tag=f"300vw-{','.join(train_v)}"), desc


SPEC = TableSpec(name="table3", title="Table 3 (300-VW faces)", rows=tuple(PAPER), paper=PAPER, load=load,
                 iterations=(14_000, 3000, 300), metric="NE", error=normalized_error, real_name="300vw",
                 frame="centred per frame, z sign per frame, scaled back by the ground truth's xy norm")


def main(argv: list[str] | None = None) -> int:
    return harness_main(SPEC, argv)


if __name__ == "__main__":
    sys.exit(main())
