"""PRN paper, Table 3: normalised error (NE) of 3D faces from 2D landmarks (68 landmarks).

    python -m benchmarks.table3 [--data synthetic|300vw|aflw2000] [--root DIR] [--quick] [--iterations N]
                                [--methods NAME,NAME] [--direct rank3,pr,empnd] [--validate] [--out DIR]
                                [--resume | --retrain]

The data, the first found under ``--root`` / ``$NRSFM_DATA``:

- ``300vw``: the 3D landmarks of the 300-VW videos (:mod:`nrsfm.datasets.faces`), split into 32 training and 32
  test videos (:func:`~nrsfm.datasets.faces.split_300vw`); the 2D input is their xy. The "+NN" rows solve each
  training video (cut as :func:`baselines.labels.multiview_cuts` cuts one-camera recordings).
- ``aflw2000``: AFLW2000-3D's real faces (:mod:`nrsfm.datasets.aflw`), an image collection: the first 75% of the
  faces in the file train, the rest test, whatever the file's length. Two sections, one per 2D input: ``fitted``
  (the fitted 3D landmarks' own x, y) and ``reannotated`` (the hand-corrected 2D, a detector-like input; the 3D
  centred on it); the data term compares each network's xy with its own input. The "+NN" rows solve the training
  faces as a collection cut into five chunks (every fifth face). NE is also given per head-yaw band (0-30, 30-60,
  60-90 degrees), and the per-sequence solvers ``--direct`` (rigid, PR, EM-PND) are run on the test faces
  themselves, as one collection, beside the single-face networks.
- without data: the embedded stand-in, synthetic 68-landmark faces (identity, expression and head rotation;
  :func:`nrsfm.datasets.synthetic.face_sequences`), half for training and half for test.

The paper's settings for 300-VW carry over: lambda 0.05, lr 1e-4 x0.8 every 5,000 iterations, 14,000 iterations,
a minibatch of 128 frames drawn at random across the training data as one alignment group (the paper splits
minibatches into 4 groups for Human3.6M and SURREAL only). C3DPO: minibatch 256 for 2,000 iterations (about
450 passes over AFLW's training faces) with the learning rate chosen for Table 1 on a held-out training subject
of Human3.6M; the drops of its schedule scaled to those iterations. ``--validate`` trains on the first 80% of the
training faces and reports on the remaining 20%, for choosing a setting without the test faces. NE per frame (:func:`benchmarks.harness.normalized_error`),
frame-weighted over the test sequences.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from benchmarks.harness import TableSpec, main as harness_main, normalized_error
from benchmarks.registry import Split

PAPER = {"PRN w/o reg": 0.5201, "CSF2 + NN": 0.2751, "PR + NN": 0.2730, "C3DPO": 0.1715, "PRN-FCN": 0.1512,
         "GT 3D": 0.0441}
#: Every row of Table 3, and two more "+NN" rows on the same footing (SPM's and EM-PND's labels).
ROWS = ("PRN w/o reg", "CSF2 + NN", "PR + NN", "SPM + NN", "EM-PND + NN", "C3DPO", "PRN-FCN", "GT 3D")
#: One alignment group of 128 frames per minibatch (the paper splits into groups on Human3.6M and SURREAL only).
FACE_GROUPS = {"groups": 1, "group_size": 128}
#: ``--validate``: the share of the training faces that trains; the rest validates.
VALIDATION_TRAIN = 0.8
#: C3DPO's learning rate on faces: Table 1's, chosen on Human3.6M's training subject S8 held out (no face read).
C3DPO_LR = 1e-2


def load(args: argparse.Namespace) -> tuple[Split | dict[str, Split], dict]:
    if args.data == "synthetic":
        from nrsfm.datasets.synthetic import face_sequences

        n, frames = (4, 100) if args.quick else (12, 300)
        seqs = face_sequences(2 * n, frames, seed=args.seed)
        train, test = seqs[:n], seqs[n:]
        desc = {"data": "synthetic faces", "train_sequences": n, "test_sequences": n, "frames": frames}
        return Split(train, train, test, test, "gt-ortho", sampling="random",
                     tag=f"faces-{n}-{frames}-{args.seed}"), desc
    if args.data == "aflw2000":
        return load_aflw(args)
    from nrsfm.datasets.faces import list_300vw, load_300vw, split_300vw

    train_v, test_v = split_300vw(list_300vw(args.root))
    if not train_v or not test_v:
        raise FileNotFoundError("300vw-3d: expected at least two videos with 3D landmarks")
    train = [load_300vw(v, args.root) for v in train_v]
    test = [load_300vw(v, args.root) for v in test_v]
    desc = {"data": "300vw", "train_videos": train_v, "test_videos": test_v}
    return Split(train, train, test, test, "gt-ortho", sampling="random",
                 tag=f"300vw-{','.join(train_v)}"), desc


def load_aflw(args: argparse.Namespace) -> tuple[dict[str, Split], dict]:
    """AFLW2000-3D's two sections (``fitted``, ``reannotated``): the first 75% of the faces train, the rest test;
    with ``--validate`` the first 80% of those training faces train and the rest of them validate."""
    from nrsfm.datasets.aflw import INPUTS, load_aflw2000, split_aflw2000

    sections, desc = {}, {"data": "aflw2000", "validate": bool(getattr(args, "validate", False))}
    for inp in INPUTS:
        train, test = split_aflw2000(load_aflw2000(args.root, input=inp))
        if desc["validate"]:
            train, test = split_aflw2000(train, VALIDATION_TRAIN)
        sections[inp] = Split([train], [train], [test], [test], "gt-ortho", sampling="random",
                              tag=f"aflw2000-{inp}-{train.meta['faces']}-{test.meta['first_face']}-{test.n_frames}")
        desc.update({f"{inp}_train_faces": train.n_frames, f"{inp}_test_faces": test.n_frames,
                     "first_test_face": int(test.meta["first_face"])})
    desc["evaluated"] = "validation faces (the last 20% of the training faces)" if desc["validate"] else "test faces"
    return sections, desc


def yaw_bands(truth) -> np.ndarray:
    """`(F,)` head-yaw band of each face of an AFLW2000-3D sequence (None-like "all" for other data)."""
    from nrsfm.datasets.aflw import face_yaw, yaw_band

    if "yaw" not in truth.meta:
        return np.full(truth.n_frames, "all")
    return yaw_band(face_yaw(truth))


SPEC = TableSpec(name="table3", title="Table 3 (faces, 68 landmarks)", rows=ROWS, paper=PAPER, load=load,
                 iterations=(14_000, 3000, 300), metric="NE", error=normalized_error, real_name="300vw",
                 real_data=(("300vw", ("300vw-3d",)), ("aflw2000", ("aflw2000",))),
                 frame="centred per frame, z sign per frame, scaled back by the ground truth's xy norm",
                 context={**FACE_GROUPS, "c3dpo_iterations": 2000, "c3dpo_batch": 256}, synthetic_context=FACE_GROUPS,
                 bands=yaw_bands, band_name="head yaw band (degrees; faces)", direct=("rank3", "pr", "empnd"),
                 c3dpo_lr=C3DPO_LR, validate=True)


def main(argv: list[str] | None = None) -> int:
    return harness_main(SPEC, argv)


if __name__ == "__main__":
    sys.exit(main())
