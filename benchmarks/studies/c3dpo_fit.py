"""A trained C3DPO's 3D error on its own training data beside its test error.

    python -m benchmarks.studies.c3dpo_fit MODEL [--root DIR] [--input gt-ortho|gt-persp] [--fraction 0.17]
                                           [--c3dpo-inputs hip|centred|prn] [--subjects S8,S9] [--seed 0] [--out DIR]

MODEL is a ``model.pt`` that ``benchmarks.table1`` trained (under ``<out>/cache/C3DPO-*/``). The keypoints are
prepared as the harness prepares them for C3DPO (:func:`benchmarks.methods.c3dpo_inputs`; ``--c3dpo-inputs`` as
when the model was trained), and the predictions are scored with PRN's protocol (MPJPE, mm) on a random
``fraction`` of the training sequences (S1, S5-S8; drawn with ``seed``) and on every test sequence. C3DPO never
sees 3D, so a training error as high as the test error says the model's objective settles there on its own
training data: the error is not over-fitting. Beside each, the mean distance between the image coordinates of
the model's camera-frame shapes and the input keypoints (the table takes the input's and only the shapes' depth),
and below, how well a linear basis of the model's size fits the training share's ground truth at best.
``--subjects`` scores the model on each named subject alone as well, in PRN's protocol and C3DPO's
(:func:`benchmarks.table1.evaluate_c3dpo`): a model trained with a subject held out (``--validate``) is scored on
the held-out subject and on the test subject, a model trained on every training subject on each of them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import markdown_table, run_metadata, run_table, write_json
from benchmarks.methods import C3DPO_INPUTS
from nrsfm.errors import ValidationError


def mpjpe_of(model, sequences: list, unit: float, inputs: str) -> tuple[float, int]:
    """PRN-protocol MPJPE (mm) of ``model`` over ``sequences`` and their frame count, scaled back as the harness
    scales C3DPO's test predictions (:func:`benchmarks.methods.c3dpo_test_predictions`)."""
    from benchmarks.methods import c3dpo_test_predictions
    from benchmarks.registry import Split, millimetres
    from nrsfm.metrics import mpjpe_prn

    preds = c3dpo_test_predictions(model, Split([], [], sequences, sequences, "gt-ortho"), unit, inputs)
    pred = np.concatenate(millimetres(preds, sequences))
    truth = np.concatenate([s.points_3d for s in sequences])
    return mpjpe_prn(pred, truth), len(truth)


def reprojection_of(model, sequences: list, unit: float, inputs: str) -> float:
    """Mean distance (mm, in the frame :func:`mpjpe_of` scores) between the image coordinates of ``model``'s
    camera-frame shapes ``R X`` and its input keypoints, over the visible points of ``sequences``: how well the
    shapes whose depth the table scores fit their own 2D input."""
    from benchmarks.methods import c3dpo_predict
    from prn.data import denormalize

    total, count = 0.0, 0
    for s in sequences:
        given = denormalize(c3dpo_predict(model, s, unit, inputs), s.points_3d)[..., :2]
        own = denormalize(c3dpo_predict(model, s, unit, inputs, replace_keypoints_with_input=False),
                          s.points_3d)[..., :2]
        vis = s.weights > 0
        total += float(np.linalg.norm(own - given, axis=-1)[vis].sum())
        count += int(vis.sum())
    return total / max(count, 1)


def basis_floor(shapes: np.ndarray, basis: int, rounds: int = 5) -> tuple[float, float]:
    """How well any ``basis``-shape linear model (a mean and ``basis`` shapes, as C3DPO's) can fit `(N, P, 3)`
    ground-truth shapes (mm): each centred shape rotated onto the mean shape (``rounds`` alignments of
    :func:`nrsfm.procrustes.align`: onto the first shape, then sweeps onto the mean), their principal ``basis``
    components fitted and rotated back. Returns the mean 3D point error and the mean error of its image coordinates
    (mm): a reference for the model's fit, not a strict bound (a basis fitted to the 2D alone, with rotations of its
    own, can fit the image coordinates closer)."""
    import torch

    from nrsfm.procrustes import align

    x = shapes - shapes.mean(axis=1, keepdims=True)
    al = align(torch.as_tensor(np.swapaxes(x, 1, 2))[None], max_iter=rounds - 1, newton=False)
    aligned, rot = np.swapaxes(al.aligned[0].numpy(), 1, 2), al.rotations[0].numpy()  # aligned = x @ rot^T
    flat = aligned.reshape(len(x), -1)
    mean = flat.mean(axis=0)
    comps = np.linalg.svd(flat - mean, full_matrices=False)[2][:basis]
    fitted = (mean + (flat - mean) @ comps.T @ comps).reshape(x.shape) @ rot
    return float(np.linalg.norm(fitted - x, axis=2).mean()), float(np.linalg.norm((fitted - x)[..., :2], axis=2).mean())


def subject_rows(model, root, subjects: list[str], input_type: str, stride: int, unit: float, inputs: str
                 ) -> list[list]:
    """For each subject: its name, ``model``'s MPJPE (mm) in PRN's protocol and in C3DPO's, and its frame count."""
    from benchmarks.methods import c3dpo_test_predictions
    from benchmarks.registry import Split
    from benchmarks.table1 import evaluate, evaluate_c3dpo
    from nrsfm.datasets import h36m

    missing = [s for s in subjects if not (root / s).is_dir()]
    if missing:
        raise ValidationError(f"--subjects: expected subjects under {root}, missing {missing}")
    rows = []
    for subject in subjects:
        seqs = h36m.load_h36m(root, [subject], input=input_type, stride=stride, source_fps=50.0)
        preds = c3dpo_test_predictions(model, Split([], [], seqs, seqs, input_type), unit, inputs)
        prn, frames = evaluate(preds, seqs)["Avg"]
        rows.append([subject, prn, evaluate_c3dpo(preds, seqs)["Avg"][0], frames])
    return rows


def main(argv: list[str] | None = None) -> int:
    from baselines.c3dpo import load_c3dpo
    from benchmarks.methods import c3dpo_unit
    from nrsfm.datasets import find_dataset, h36m

    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.c3dpo_fit")
    p.add_argument("model", help="a C3DPO model.pt written by benchmarks.table1")
    p.add_argument("--root", default=None, help="data folder holding h36m/ (default: $NRSFM_DATA)")
    p.add_argument("--input", default="gt-ortho", choices=("gt-ortho", "gt-persp"))
    p.add_argument("--fraction", type=float, default=0.17, help="share of the training sequences scored")
    p.add_argument("--c3dpo-inputs", default="hip", choices=C3DPO_INPUTS,
                   help="as --c3dpo-inputs of benchmarks.table1 when the model was trained")
    p.add_argument("--stride", type=int, default=1, help="Human3.6M frame stride (5 for the public 50 fps files)")
    p.add_argument("--subjects", default="", help="comma-separated subjects scored one by one (e.g. S8,S9)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/c3dpo_fit")
    args = p.parse_args(argv)

    def run(args: argparse.Namespace) -> int:
        if not 0 < args.fraction <= 1:
            raise ValidationError(f"--fraction: expected a share in (0, 1], got {args.fraction}")
        if not Path(args.model).is_file():
            raise ValidationError(f"{args.model}: no such model file; give the model.pt under "
                                  "<out>/cache/C3DPO-*/ of a benchmarks.table1 run")
        root = find_dataset("h36m", args.root)
        train, test = (h36m.load_h36m(root, list(subjects), input=args.input, stride=args.stride, source_fps=50.0)
                       for subjects in (h36m.TRAIN_SUBJECTS,
                                        [t for t in h36m.TEST_SUBJECTS if (root / t).is_dir()]))
        unit = c3dpo_unit(train, args.c3dpo_inputs)
        model = load_c3dpo(args.model, "cpu")
        rng = np.random.default_rng(args.seed)
        chosen = [train[i] for i in np.sort(rng.choice(len(train), max(1, round(args.fraction * len(train))),
                                                       replace=False))]
        rows = [[name, *mpjpe_of(model, seqs, unit, args.c3dpo_inputs),
                 reprojection_of(model, seqs, unit, args.c3dpo_inputs)]
                for name, seqs in (("training (a random share)", chosen), ("test", test))]
        print(markdown_table(["sequences", "MPJPE (mm, PRN protocol)", "frames",
                              "the shapes' 2D reprojection error (mm)"], rows))
        by_subject = subject_rows(model, root, [s.strip() for s in args.subjects.split(",") if s.strip()],
                                  args.input, args.stride, unit, args.c3dpo_inputs)
        if by_subject:
            print("\n" + markdown_table(["subject", "MPJPE (mm, PRN protocol)", "MPJPE (mm, C3DPO protocol)",
                                         "frames"], by_subject))
        floor = basis_floor(np.concatenate([s.points_3d for s in chosen]), model.config.basis)
        print(f"\nA {model.config.basis}-shape basis fitted to the ground truth of the training share (each shape "
              f"rotated onto the mean shape): 3D error {floor[0]:.1f} mm, its image coordinates {floor[1]:.1f} mm")
        write_json(Path(args.out) / "c3dpo_fit.json", {"meta": run_metadata(model=str(args.model), input=args.input,
                                                                          fraction=args.fraction, seed=args.seed),
                                                        "results": rows, "subjects": by_subject,
                                                        "basis_floor_mm": {"3d": floor[0],
                                                                                            "xy": floor[1]}})
        return 0

    return run_table("c3dpo_fit", run, args)


if __name__ == "__main__":
    sys.exit(main())
