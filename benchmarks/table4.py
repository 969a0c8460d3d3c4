"""PRN paper, Table 4: normalised error (NE) of dense 3D bodies from 2D, SURREAL (SMPL meshes, 6,890 points).

    python -m benchmarks.table4 [--data synthetic|surreal] [--root DIR] [--quick] [--iterations N]
                                [--methods NAME,NAME] [--out DIR] [--resume | --retrain]

Real data: vertex sequences exported from SURREAL (:mod:`nrsfm.datasets.surreal`: ``surreal/train/*.npz`` and
``surreal/test/*.npz``), each frame seen by an orthographic camera turned at random about the vertical axis.
As the paper: 4,096 hidden units, and the PR loss computed on random groups of points (8 groups, re-drawn every
iteration) because the alignment of all 6,890 points per frame is too heavy; groups of consecutive frames. The
paper does not state the iterations; 70,000 as for Human3.6M. NE per frame, frame-weighted.

Without data: the embedded stand-in, dense deforming tubes (:func:`nrsfm.datasets.synthetic.surface_sequence`,
1,200 points; 300 with ``--quick``), with 1,024 hidden units and 4 point groups.
"""

from __future__ import annotations

import argparse
import sys

from benchmarks.harness import TableSpec, main as harness_main, normalized_error
from benchmarks.registry import Split

PAPER = {"PRN w/o reg": 0.3565, "C3DPO": 0.3509, "PRN-FCN": 0.1377}


def load(args: argparse.Namespace) -> tuple[Split, dict]:
    if args.data == "synthetic":
        from nrsfm.datasets.synthetic import surface_sequence

        (n_train, n_test), frames, (nu, nv) = ((6, 2), 64, (20, 15)) if args.quick else ((12, 4), 120, (40, 30))
        seqs = [surface_sequence(frames, nu, nv, seed=args.seed + i, name=f"tube{i:02d}")
                for i in range(n_train + n_test)]
        train, test = seqs[:n_train], seqs[n_train:]
        desc = {"data": "synthetic dense tubes", "train_sequences": n_train, "test_sequences": n_test,
                "frames": frames, "points": nu * nv}
        return Split(train, train, test, test, "gt-ortho", sampling="consecutive",
                     tag=f"tubes-{n_train}-{n_test}-{frames}-{nu}x{nv}-{args.seed}"), desc
    from nrsfm.datasets.surreal import load_surreal

    train, test = load_surreal("train", args.root, seed=args.seed), load_surreal("test", args.root, seed=args.seed)
    desc = {"data": "surreal", "train_clips": [s.name for s in train], "test_clips": [s.name for s in test],
            "points": train[0].n_points}
    return Split(train, train, test, test, "gt-ortho", sampling="consecutive",
                 tag=f"surreal-{len(train)}-{len(test)}-{args.seed}"), desc


SPEC = TableSpec(name="table4", title="Table 4 (SURREAL dense bodies)", rows=tuple(PAPER), paper=PAPER, load=load,
                 iterations=(70_000, 3000, 300), metric="NE", error=normalized_error, real_name="surreal",
                 real_data=(("surreal", ("surreal/train", "surreal/test")),),
                 context={"width": 4096, "point_groups": 8}, synthetic_context={"width": 1024, "point_groups": 4},
                 frame="centred per frame, z sign per frame, scaled back by the ground truth's xy norm")


def main(argv: list[str] | None = None) -> int:
    return harness_main(SPEC, argv)


if __name__ == "__main__":
    sys.exit(main())
