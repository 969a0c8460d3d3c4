"""PRN paper, Table 1: MPJPE (mm) on Human3.6M from 2D inputs, per action.

    python -m benchmarks.table1 [--data synthetic|h36m] [--root DIR] [--input gt-ortho|gt-persp|sh|all]
                                [--quick] [--out DIR] [--iterations N] [--methods NAME,NAME] [--stride auto|1|5]
                                [--resume | --retrain]

Protocol (PRN official test code, see nrsfm.metrics.mpjpe_prn): train on S1,
S5, S6, S7, S8 and test on S9 and S11 (whichever are present; the output
says which), 10 fps, 17 joints; inputs and outputs normalised per frame by
the xy Frobenius norm and scaled back by the ground truth's; shapes centred
on the joints' mean; z sign chosen per frame; no Procrustes. Per action the
frame-weighted mean over subjects, cameras and sub-actions; "Avg" the
frame-weighted mean over all test frames.

With no arguments it runs on the embedded synthetic stand-in (articulated
humans, 4 ring cameras, subjects S1-S11, six motion families); its numbers
are not comparable with the paper's, which are printed beside them for
orientation only. Trained models are cached under ``<out>/cache`` by
configuration, so a rerun evaluates without retraining.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import (add_training_arguments, choose_data, labels_dir, markdown_table, run_metadata,
                               run_table, write_csv, write_json)
from benchmarks.methods import C3DPO_INPUTS, PRN_L_EMA, methods
from benchmarks.registry import (QUICK_LABEL_PARAMS, NotRun, RunContext, Split, millimetres,
                                 schedule_text)
from nrsfm.datasets import h36m
from nrsfm.errors import ValidationError
from nrsfm.metrics import mpjpe_prn_per_frame

log = logging.getLogger("benchmarks.table1")

#: Paper column order and the Human3.6M action of each column.
PAPER_COLUMNS = ("Directions", "Discussion", "Eating", "Greeting", "Phoning", "Posing", "Purchases", "Sitting",
                 "SittingDown", "Smoking", "Photo", "Waiting", "Walking", "WalkDog", "WalkTogether")
#: Published numbers (PRN, ECCV 2020, Table 1): 15 actions in PAPER_COLUMNS order, then Avg.
PAPER = {
    ("PRN w/o reg", "gt-ortho"): (138.1, 139.7, 146.5, 145.2, 140, 127.6, 149.4, 170.4, 188.4, 138.3, 150.9, 133.1,
                                  125.6, 143.9, 139.3, 144.8),
    ("CSF2 + NN", "gt-ortho"): (87.2, 90.1, 96.1, 95.9, 102.9, 92.1, 99.3, 129.8, 136.7, 99.5, 120.1, 95.2, 90.8,
                                102.4, 89.2, 101.6),
    ("SPM + NN", "gt-ortho"): (65.3, 68.7, 82.0, 70.1, 95.3, 65.1, 71.9, 117.0, 136.0, 84.3, 88.9, 71.2, 59.5, 73.3,
                               68.3, 82.3),
    ("C3DPO", "gt-ortho"): (56.1, 55.6, 62.2, 66.4, 63.2, 62.0, 62.9, 76.3, 85.8, 59.9, 88.7, 63.3, 71.1, 70.7, 72.3,
                            67.8),
    ("PRN-FCN", "gt-ortho"): (65.3, 58.2, 60.5, 73.8, 60.7, 71.5, 64.6, 79.8, 90.2, 60.3, 81.2, 67.1, 54.4, 61.2,
                              65.6, 66.7),
    ("C3DPO", "gt-persp"): (96.8, 85.7, 85.8, 107.1, 86.0, 96.8, 93.9, 94.9, 96.7, 86.0, 124.3, 90.7, 95.2, 93.4,
                            101.3, 95.6),
    ("PRN-FCN", "gt-persp"): (93.1, 83.3, 76.2, 98.6, 78.8, 91.7, 81.4, 87.4, 91.6, 78.2, 104.3, 89.6, 83.0, 80.5,
                              95.3, 86.4),
    ("C3DPO", "sh"): (131.1, 137.4, 125.2, 146.4, 143.2, 141.4, 137.3, 141.4, 163.8, 136.2, 161, 143.4, 145.9, 153.2,
                      168.6, 145.0),
    ("PRN-FCN", "sh"): (100.2, 89.4, 83.8, 105.5, 93.0, 97.2, 89.2, 114.0, 141.2, 89.1, 114.8, 97.3, 91.0, 88.3,
                        107.2, 99.1),  # SH fine-tuned detections (SH FT), as in the copy we evaluate on
    ("PRN-FCN-W", "sh"): (100.3, 88.8, 82.8, 105.2, 91.4, 96.7, 88.1, 102.1, 113.2, 87.4, 115.1, 96.5, 91.7, 87.6,
                          106.4, 95.9),
}
#: The protocol of each published number: C3DPO's rows are the C3DPO README's figures in its own evaluation (each
#: Avg the unweighted mean of its 15 actions); the paper's own rows are in PRN's.
PROTOCOLS = ("prn", "c3dpo")
PAPER_PROTOCOL = {key: "c3dpo" if key[0] == "C3DPO" else "prn" for key in PAPER}
PROTOCOL_TEXT = {
    "prn": "PRN protocol (shapes centred on the joints' mean, z sign per frame, no Procrustes; frame-weighted means)",
    "c3dpo": "C3DPO protocol (shapes centred on the hip, the better of the raw and the depth-flipped prediction per "
             "frame, no Procrustes; the mean per action, Avg the unweighted mean of the actions)"}
INPUTS = ("gt-ortho", "gt-persp", "sh")
#: The rows run by default: the paper's, the GT 3D bound, PR + NN and this toolbox's PRN-L (``--methods`` adds the
#: other registered rows, e.g. ``EM-PND + NN``).
ROWS = ("PRN w/o reg", "CSF2 + NN", "SPM + NN", "PR + NN", "C3DPO", "PRN-FCN", "PRN-FCN-W", "PRN-L", "GT 3D")
#: C3DPO's learning rate in this table: of 1e-3 (the authors'), 3e-3, 1e-2 and 3e-2 the lowest error on the training
#: subject S8 held out (``--validate S8``, the authors' hip-normalised inputs, 3,000 iterations of batch 256;
#: ``benchmarks/RESULTS.md``), never on the test subjects.
C3DPO_LR = 1e-2
SYNTHETIC_FRAMES = 200
QUICK_FRAMES = 60
#: ``--quick``: three motion families (the pseudo-labels' light settings are
#: :data:`benchmarks.registry.QUICK_LABEL_PARAMS`).
QUICK_MOTIONS = ("walking", "sitting_down", "waving")
#: The stand-in's motion families (None: all of them).
SYNTHETIC_MOTIONS: tuple[str, ...] | None = None


# --------------------------------------------------------------------------- data
def split_subjects(args: argparse.Namespace, train_s: list[str], test_s: list[str]) -> tuple[list[str], list[str]]:
    """The training and evaluation subjects: ``test_s``, or with ``--validate S`` the training subject ``S`` held
    out of training and evaluated on in their place (to choose a setting without the test subjects)."""
    held = getattr(args, "validate", None)
    if held is None:
        return list(train_s), list(test_s)
    if held not in train_s or len(train_s) < 2:
        raise ValidationError(f"--validate: expected one of the training subjects {list(train_s)} (and at least one "
                              f"other to train on), got {held!r}")
    return [s for s in train_s if s != held], [held]


def load_splits(args: argparse.Namespace, inputs: tuple[str, ...]) -> tuple[dict[str, Split], dict]:
    """The train/test data of every input type, and a description for the metadata."""
    data_notice(args)
    if args.data == "synthetic":
        from nrsfm.datasets.synthetic import SUBJECTS, human_sequences

        frames = QUICK_FRAMES if args.quick else SYNTHETIC_FRAMES
        takes = 1 if args.quick else 2
        assert set(h36m.TRAIN_SUBJECTS + h36m.TEST_SUBJECTS) <= set(SUBJECTS)
        train_s, test_s = split_subjects(args, h36m.TRAIN_SUBJECTS, h36m.TEST_SUBJECTS)
        held = getattr(args, "validate", None)
        tag = f"synthetic-{frames}-{takes}-{args.seed}" + (f"-val{held}" if held else "")
        desc = {"data": "synthetic", "train_subjects": train_s, "test_subjects": test_s,
                "frames_per_clip": frames, "fps": 10, "takes": takes}
        splits = {}
        for inp in inputs:
            kw = {"projection": "orthographic" if inp == "gt-ortho" else "perspective", "n_frames": frames,
                  "takes": takes, "seed": args.seed}
            if SYNTHETIC_MOTIONS is not None or args.quick:
                kw["motions"] = SYNTHETIC_MOTIONS or QUICK_MOTIONS
            tr = human_sequences(train_s, **kw)
            te = human_sequences(test_s, **kw)
            if inp == "sh":  # detector-like noise, and no Neck/Nose detection (16 of 17 points), as SH
                tr_in = [_drop_neck(s) for s in human_sequences(train_s, noise=8.0, **kw)]
                te_in = [_drop_neck(s) for s in human_sequences(test_s, noise=8.0, **kw)]
                splits[inp] = Split(tr_in, tr, te_in, te, inp, tag=f"{tag}-sh", targets_labels_tag=f"{tag}-gt-persp")
            else:
                splits[inp] = Split(tr, tr, te, te, inp, tag=f"{tag}-{inp}")
        return splits, desc
    from nrsfm.datasets import find_dataset

    root = find_dataset("h36m", args.root)
    present = {p.name for p in root.iterdir() if p.is_dir()}
    train_s = [s for s in h36m.TRAIN_SUBJECTS if s in present]
    test_s = [s for s in h36m.TEST_SUBJECTS if s in present]
    if not train_s or not test_s:
        raise ValidationError(f"{root}: expected training subjects {h36m.TRAIN_SUBJECTS} and test subjects "
                              f"{h36m.TEST_SUBJECTS}, found {sorted(present)}")
    missing_test = [s for s in h36m.TEST_SUBJECTS if s not in present]
    train_s, test_s = split_subjects(args, train_s, test_s)
    stride = h36m.detect_stride(root, test_s[0]) if args.stride == "auto" else int(args.stride)
    fps = 50.0  # the public files' rate; the loaders report fps = 50 / stride
    desc = {"data": "h36m", "root": str(root), "train_subjects": train_s, "test_subjects": test_s,
            "missing_test_subjects": missing_test, "stride": stride,
            "stride_rule": args.stride}
    cache: dict[str, list] = {}

    def load(subjects, inp):
        key = f"{','.join(subjects)}|{inp}"
        if key not in cache:
            cache[key] = h36m.load_h36m(root, subjects, input=inp, stride=stride, source_fps=fps)
        return cache[key]

    splits = {}
    for inp in inputs:
        tag = f"h36m-{','.join(train_s)}-{stride}-{inp}"
        # pseudo-labels are cached per cut (its recording, offset and 2D): every choice of training subjects
        # shares them
        labels_tag = f"h36m-{stride}-{inp}"
        if inp == "sh":
            te_in = load(test_s, "sh")
            names = {s.name for s in te_in}
            te_gt = [s for s in load(test_s, "gt-persp") if s.name in names]
            tr_in = load(train_s, "sh")
            tr_names = {s.name for s in tr_in}
            tr_gt = [s for s in load(train_s, "gt-persp") if s.name in tr_names]
            splits[inp] = Split(tr_in, tr_gt, te_in, te_gt, inp, tag=tag, labels_tag=labels_tag,
                                targets_labels_tag=f"h36m-{stride}-gt-persp")
        else:
            tr, te = load(train_s, inp), load(test_s, inp)
            splits[inp] = Split(tr, tr, te, te, inp, tag=tag, labels_tag=labels_tag)
    return splits, desc


def _drop_neck(seq):
    vis = np.ones((seq.n_frames, seq.n_points))
    vis[:, h36m.JOINT_NAMES.index("Neck/Nose")] = 0.0
    return seq.replace(visibility=vis, meta={**seq.meta, "input": "sh"})


# --------------------------------------------------------------------------- evaluation
def evaluate(preds: list[np.ndarray], truth: list) -> dict[str, tuple[float, int]]:
    """Per action (and "Avg") the frame-weighted MPJPE (mm) and the frame count."""
    errs: dict[str, list[np.ndarray]] = defaultdict(list)
    for p, seq in zip(millimetres(preds, truth), truth):
        e = mpjpe_prn_per_frame(p, seq.points_3d)
        errs[seq.meta.get("action", "all")].append(e)
        errs["Avg"].append(e)
    return {a: (float(np.concatenate(v).mean()), int(sum(len(x) for x in v))) for a, v in errs.items()}


def evaluate_c3dpo(preds: list[np.ndarray], truth: list) -> dict[str, tuple[float, int]]:
    """C3DPO's protocol (its ``eval_h36m``): per action (and "Avg") the mean over its frames of the MPJPE (mm)
    after centring on the hip, the better of the raw and the depth-flipped prediction per frame; "Avg" is the
    unweighted mean of the actions' errors. Also "stress" (mm, the same averaging)."""
    from benchmarks.methods import root_joint
    from nrsfm.metrics import mpjpe_best_flip_per_frame, stress_per_frame

    errs: dict[str, list[np.ndarray]] = defaultdict(list)
    stresses: dict[str, list[np.ndarray]] = defaultdict(list)
    for p, seq in zip(millimetres(preds, truth), truth):
        action = seq.meta.get("action", "all")
        errs[action].append(mpjpe_best_flip_per_frame(p, seq.points_3d, root=root_joint(seq)))
        stresses[action].append(stress_per_frame(p, seq.points_3d))
    out = {a: (float(np.concatenate(v).mean()), int(sum(len(x) for x in v))) for a, v in errs.items()}
    out["Avg"] = (float(np.mean([v[0] for v in out.values()])), int(sum(v[1] for v in out.values())))
    out["stress"] = (float(np.mean([np.concatenate(v).mean() for v in stresses.values()])), out["Avg"][1])
    return out


def _columns(data: str, results: dict) -> list[str]:
    if data == "h36m":
        return list(PAPER_COLUMNS)
    acts = sorted({a for per in results.values() for a in per if a != "Avg"})
    return acts


def parser(prog: str = "python -m benchmarks.table1", description: str | None = None) -> argparse.ArgumentParser:
    """The command line of this table (also read by studies that evaluate its rows)."""
    p = argparse.ArgumentParser(prog=prog, description=description or __doc__.split("\n\n")[0])
    p.add_argument("--data", choices=["synthetic", "h36m"], default=None,
                   help="default: h36m when the data folder holds h36m/, else the embedded synthetic stand-in")
    p.add_argument("--root", help="data folder holding h36m/ (default: $NRSFM_DATA)")
    p.add_argument("--input", choices=list(INPUTS) + ["all"], default="gt-ortho")
    p.add_argument("--quick", action="store_true", help="a short schedule and small data: a smoke run")
    p.add_argument("--iterations", type=int, default=None,
                   help="training iterations (default: 70000 for h36m as the paper, 4000 synthetic, 300 quick)")
    p.add_argument("--methods", default=None, help=f"comma-separated rows (default: {', '.join(ROWS)}; any "
                                                   "registered row)")
    p.add_argument("--out", default=None, help="output folder (default: runs/table1-<data>)")
    p.add_argument("--stride", default="auto", help="Human3.6M frame stride: 5 for 50 fps files, 1 for 10 fps "
                                                    "copies, auto to detect")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="parallel solves of the pseudo-label pipeline, one BLAS thread each (default: every core)")
    p.add_argument("--c3dpo-iterations", type=int, default=None,
                   help="C3DPO's iterations (default: its 90-epoch schedule scaled as --iterations scales PRN's 70k)")
    p.add_argument("--c3dpo-batch", type=int, default=None, help="C3DPO's minibatch (default: the authors' 1024; "
                                                                   "128 with --quick)")
    p.add_argument("--c3dpo-rescale", type=float, default=1.0,
                   help="C3DPO's keypoint_rescale: the centred keypoints are multiplied by it (default 1)")
    p.add_argument("--c3dpo-lr", type=float, default=C3DPO_LR,
                   help=f"C3DPO's learning rate before its two drops (default {C3DPO_LR:g}: of the authors' 1e-3, 3e-3, "
                        "1e-2 and 3e-2 the lowest error on the training subject S8 held out, --validate S8; "
                        "benchmarks/RESULTS.md)")
    p.add_argument("--c3dpo-precision", choices=["fp32", "bf16"], default="fp32",
                   help="C3DPO's trunks in float32 (default) or under bfloat16 autocast (about 3 times faster on a "
                        "CPU with AVX-512 BF16; the losses and weights stay float32)")
    p.add_argument("--c3dpo-optimizer", choices=["sgd", "adam"], default="sgd",
                   help="C3DPO's optimiser: the authors' Human3.6M SGD (default) or Adam, their code's other breed")
    p.add_argument("--c3dpo-repeat", type=int, default=1,
                   help="use each C3DPO minibatch for this many consecutive iterations (default 1; 8 is how the "
                        "authors' data loader ran: baselines.c3dpo)")
    p.add_argument("--c3dpo-monitor", action="store_true",
                   help="also evaluate C3DPO on the test split at every checkpoint, into its train.json (a "
                        "diagnostic of the error along training; nothing is chosen with it)")
    p.add_argument("--c3dpo-eager", action="store_true",
                   help="on a GPU, launch C3DPO's training iterations op by op instead of replaying each as a CUDA "
                        "graph (the same arithmetic, fewer kernel launches)")
    p.add_argument("--c3dpo-compile", action="store_true",
                   help="compile C3DPO's forward and backward passes with torch.compile (fewer, fused kernels: "
                        "faster on a GPU once compiled; the compilation takes a minute or more)")
    p.add_argument("--c3dpo-inputs", choices=list(C3DPO_INPUTS), default="hip",
                   help="C3DPO's inputs: hip (the authors', after Kudo et al.: each frame centred on the hip and "
                        "divided by its mean hip-to-joint distance, the 3D and the error in millimetres through the "
                        "same scale of the ground truth; default), centred (centred, every frame divided by one "
                        "global scale) or prn (each frame divided by its own xy norm, as the other rows)")
    p.add_argument("--label-solver", default=RunContext.label_solver,
                   help=f"PRN-L: the per-sequence solver of its pseudo-labels (default {RunContext.label_solver}); "
                        "solvers joined by '+' (pr+empnd) give the equal-weight mean of their labels")
    p.add_argument("--label-weight", type=float, default=RunContext.label_weight,
                   help=f"PRN-L: the pseudo-labels' weight beside the PR loss (default {RunContext.label_weight:g}, "
                        "chosen on S8 held out; benchmarks/RESULTS.md)")
    p.add_argument("--label-decay", choices=["linear", "none"], default=RunContext.label_decay,
                   help=f"PRN-L: the weight stays, or falls linearly to 0 by the last iteration (default "
                        f"{RunContext.label_decay}, chosen on S8 held out)")
    p.add_argument("--label-frames", choices=["as-is", "unit"], default=RunContext.label_frames,
                   help="PRN-L and the +NN rows: solve each training frame's 2D as it is (default) or centred and "
                        "scaled to a unit xy norm first (weak-perspective tracks change scale with depth and camera)")
    p.add_argument("--label-source", choices=["inputs", "targets"], default=None,
                   help="PRN-L and the +NN rows: solve the pseudo-labels from the network's 2D inputs or from the 2D "
                        "its data term compares with (they differ on SH only: detections in, ground-truth 2D as the "
                        "paper's SH networks are trained against; default: targets for PRN-L, chosen on S8 held out, "
                        "inputs for the +NN rows)")
    p.add_argument("--ema", type=float, default=RunContext.ema,
                   help="the networks return an exponential moving average of their weights after the BN freeze, "
                        "with this decay per iteration (prn.train.TrainConfig.ema; 0: the last iterate; default: "
                        f"{PRN_L_EMA} for PRN-L, chosen on S8 held out, 0 for the other rows, as the paper)")
    p.add_argument("--mirror-test", action=argparse.BooleanOptionalAction, default=None,
                   help="each test frame also goes through the network mirrored (left and right swapped, x negated) "
                        "and the two shapes are averaged, still one frame at a time (default: on for PRN-L, chosen "
                        "on S8 held out; off for the other rows, as the paper)")
    p.add_argument("--mirror-train", action=argparse.BooleanOptionalAction, default=None,
                   help="the 2D networks train on the training frames and their mirror images (labels mirrored with them; "
                        "default: on for PRN-L, chosen on S8 held out; off for the other rows, as the paper)")
    p.add_argument("--validate", metavar="SUBJECT", default=None,
                   help="hold this training subject out of training and evaluate on it instead of the test subjects "
                        "(for choosing a setting without them; no paper numbers beside it)")
    p.add_argument("--plots", action="store_true", help="also write the comparison figures (benchmarks.figures): "
                                                        "qualitative, per-action bars, training curves")
    add_training_arguments(p)
    return p


def parse_args(p: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """``argv`` read with ``p`` (:func:`parser`); :func:`run_rows` settles ``--data`` (:func:`data_notice`)."""
    return p.parse_args(argv)


def data_notice(args: argparse.Namespace) -> str | None:
    """Settle ``args.data``: h36m when ``--root`` or ``$NRSFM_DATA`` holds ``h36m/``, else the synthetic stand-in,
    whose notice is returned (:func:`benchmarks.common.choose_data`)."""
    return choose_data(args, [("h36m", ("h36m",))], "table1")


def _label_parameters(summary: dict) -> str:
    """The label table's "parameters" cell: the solver's (each mixed solver's, and the weights), and how the
    frames were solved when not as they are."""
    if "weights" in summary:
        parts = [f"{m}: {', '.join(f'{a}={b}' for a, b in p.items()) or 'defaults'}"
                 for m, p in summary["params"].items()]
        parts.append("weights " + " / ".join(f"{w:.2f}" for w in summary["weights"]))
    else:
        parts = [f"{a}={b}" for a, b in summary["params"].items()]
    if summary.get("frames_solved", "as-is") != "as-is":
        parts.append(f"{summary['frames_solved']} frames")
    return ", ".join(parts) or "defaults"


def main(argv: list[str] | None = None) -> int:
    return run_table("table1", _run, parse_args(parser(), argv))


@dataclass
class Rows:
    """What :func:`run_rows` computed: the data, the run's options, and per (row, input) the test predictions
    `(F, P, 3)` per test sequence (PRN's per-frame units; when asked for) and the per-action errors, or why a cell
    did not run."""

    splits: dict[str, Split]
    desc: dict
    ctx: RunContext
    names: list[str]
    predictions: dict[tuple[str, str], list[np.ndarray]]
    results: dict[tuple[str, str], dict[str, tuple[float, int]]]
    not_run: dict[tuple[str, str], str]
    results_c3dpo: dict[tuple[str, str], dict[str, tuple[float, int]]] = None


def run_rows(args: argparse.Namespace, keep_predictions: bool = False) -> Rows:
    """Train (or read back from the cache) and evaluate the rows of ``args`` on its inputs; the test predictions
    are kept in :attr:`Rows.predictions` only with ``keep_predictions``."""
    inputs = INPUTS if args.input == "all" else (args.input,)
    data_notice(args)
    if args.iterations is not None and args.iterations < 1:
        raise ValidationError(f"--iterations: expected a number of training iterations >= 1, got {args.iterations}")
    iterations = args.iterations or (300 if args.quick else 70_000 if args.data == "h36m" else 4000)
    registry = methods()
    names = list(ROWS) if args.methods is None else [m.strip() for m in args.methods.split(",")]
    for n in names:
        if n not in registry:
            raise ValidationError(f"--methods: expected names among {list(registry)}, got {n!r}")
    held = "" if args.validate is None else f"-validate-{args.validate}"
    out = Path(args.out or f"runs/table1-{args.data}{'-quick' if args.quick else ''}{held}")
    if args.c3dpo_batch is None:
        args.c3dpo_batch = 128 if args.quick else 1024
    if args.quick and args.c3dpo_iterations is None:  # a smoke run: C3DPO as many iterations as the other rows
        args.c3dpo_iterations = iterations
    if args.c3dpo_iterations is not None and args.c3dpo_iterations < 1:
        raise ValidationError(f"--c3dpo-iterations: expected >= 1, got {args.c3dpo_iterations}")
    if not args.c3dpo_lr > 0:
        raise ValidationError(f"--c3dpo-lr: expected a learning rate > 0, got {args.c3dpo_lr}")
    if args.c3dpo_repeat < 1:
        raise ValidationError(f"--c3dpo-repeat: expected >= 1, got {args.c3dpo_repeat}")
    if args.ema is not None and not 0 <= args.ema < 1:
        raise ValidationError(f"--ema: expected a decay in [0, 1) (0: the last iterate), got {args.ema}")
    if not args.label_weight >= 0:
        raise ValidationError(f"--label-weight: expected a weight >= 0, got {args.label_weight}")
    from nrsfm.solvers.registry import available_solvers

    from baselines.label_mix import parse_label_solvers

    if not all(name in available_solvers() for name in parse_label_solvers(args.label_solver)):
        raise ValidationError(f"--label-solver: expected one of {available_solvers()}, or several joined by '+' "
                              f"(their labels' mean, e.g. pr+empnd), got {args.label_solver!r}")
    if args.jobs < 1 or args.c3dpo_batch < 2:
        raise ValidationError(f"--jobs and --c3dpo-batch: expected >= 1 and >= 2, got {args.jobs}, {args.c3dpo_batch}")
    ctx = RunContext(out_dir=out, labels_dir=labels_dir(args), iterations=iterations, seed=args.seed,
                     progress=not args.no_progress, device=args.device, retrain=args.retrain, jobs=args.jobs,
                     c3dpo_batch=args.c3dpo_batch, c3dpo_iterations=args.c3dpo_iterations,
                     c3dpo_rescale=args.c3dpo_rescale, c3dpo_inputs=args.c3dpo_inputs,
                     c3dpo_optimizer=args.c3dpo_optimizer, c3dpo_monitor=args.c3dpo_monitor, c3dpo_lr=args.c3dpo_lr,
                     c3dpo_precision=args.c3dpo_precision, c3dpo_cuda_graph=not args.c3dpo_eager,
                     c3dpo_compile=args.c3dpo_compile, c3dpo_repeat=args.c3dpo_repeat,
                     compress_schedule=args.compress_schedule, label_solver=args.label_solver,
                     label_weight=args.label_weight, label_decay=args.label_decay, label_frames=args.label_frames,
                     ema=args.ema, mirror_test=args.mirror_test, mirror_train=args.mirror_train,
                     label_source=args.label_source, label_params=QUICK_LABEL_PARAMS if args.quick else {})
    splits, desc = load_splits(args, inputs)
    log.info("table1: %s, train %s, test %s, %d iterations", desc["data"], desc["train_subjects"],
             desc["test_subjects"], iterations)
    rows = Rows(splits, desc, ctx, names, {}, {}, {}, {})
    for inp, split in splits.items():
        for name in names:
            m = registry[name]
            if inp not in m.inputs:
                rows.not_run[(name, inp)] = f"{name} does not take {inp} input"
                continue
            log.info("training/evaluating %s on %s ...", name, inp)
            try:
                preds = m.run(split, ctx)
            except NotRun as why:
                rows.not_run[(name, inp)] = str(why)
                continue
            rows.results[(name, inp)] = evaluate(preds, split.test_truth)
            rows.results_c3dpo[(name, inp)] = evaluate_c3dpo(preds, split.test_truth)
            if keep_predictions:
                rows.predictions[(name, inp)] = preds
    return rows


def _run(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    notice = data_notice(args)
    if notice:
        print(notice, flush=True)
    rows_run = run_rows(args, keep_predictions=args.plots)
    splits, desc, ctx, names = rows_run.splits, rows_run.desc, rows_run.ctx, rows_run.names
    inputs = tuple(splits)
    results, predictions, not_run = rows_run.results, rows_run.predictions, rows_run.not_run
    out, iterations, registry = ctx.out_dir, ctx.iterations, methods()
    cols = _columns(args.data, {k: v for k, v in results.items()})
    by_protocol = {"prn": results, "c3dpo": rows_run.results_c3dpo}
    rows_csv, md = [], []
    header = ["Method"] + cols + ["Avg", "paper Avg"]
    for inp in inputs:
        evaluated = (f"test {'+'.join(desc['test_subjects'])}" if args.validate is None else
                     f"validation {args.validate} (a training subject held out of training; no test subject used)")
        for protocol in PROTOCOLS:
            md.append(f"\n### Table 1 ({inp}): MPJPE (mm), {desc['data']}, {evaluated}, {PROTOCOL_TEXT[protocol]}\n")
            md.append(markdown_table(header, _protocol_rows(protocol, inp, names, by_protocol[protocol], not_run, cols,
                                                            args, registry, rows_csv)))
    md.insert(0, f"Training: {iterations:,} iterations, {schedule_text(iterations, ctx.compress_schedule)}. "
                 "Each row is scaled back to millimetres by its own per-frame statistic of the ground truth (PRN's "
                 "rows: the xy norm; C3DPO on the authors' inputs: the mean hip distance), then scored in both "
                 "protocols; a paper number sits only in the protocol it was measured in.")
    labels = [(k, v["labels"]) for k, v in ctx.timings.items() if "labels" in v]
    if labels:
        md.append("\nPseudo-labels (training frames; MPJPE against the ground truth, PRN protocol):\n")
        md.append(markdown_table(["row", "solver", "parameters", "cuts", "failed", "labelled frames",
                                  "label MPJPE (mm)", "time in this run (s; cuts read back are not solved again)"],
                                 [[k, s["method"], _label_parameters(s), s["cuts"], s["failed"],
                                   f"{s['labelled_frames']} of {s['frames']}", s.get("label_mpjpe_mm"), s["seconds"]]
                                  for k, s in labels]))
    if notice:
        md.insert(0, notice + "; the paper columns are Human3.6M numbers, shown for orientation only.\n")
    text = "\n".join(md)
    print(text)
    total = time.perf_counter() - t_start
    meta = run_metadata(table="PRN Table 1", metric="MPJPE (mm), PRN and C3DPO protocols", data=desc,
                        inputs=list(inputs), protocols=PROTOCOL_TEXT,
                        schedule=schedule_text(iterations, ctx.compress_schedule),
                        methods=names, iterations=iterations, seed=args.seed, quick=args.quick,
                        label_params=ctx.label_params, label_frames=ctx.label_frames,
                        label_source=ctx.label_source, ema=ctx.ema,
                        mirror_test=ctx.mirror_test, mirror_train=ctx.mirror_train,
                        c3dpo={"iterations": args.c3dpo_iterations, "batch": args.c3dpo_batch,
                               "keypoint_rescale": args.c3dpo_rescale,
                               "optimizer": args.c3dpo_optimizer, "inputs": args.c3dpo_inputs,
                               "lr": args.c3dpo_lr, "precision": args.c3dpo_precision,
                               "cuda_graph": not args.c3dpo_eager, "compile": args.c3dpo_compile,
                               "repeat": args.c3dpo_repeat},
                        timings=ctx.timings, total_seconds=total)
    write_csv(out / "table1.csv", rows_csv)
    write_json(out / "table1.json", {"meta": meta, "results": [
        {"method": n, "input": i, "protocol": protocol,
         "per_action": {a: {"mpjpe_mm": v[0], "frames": v[1]} for a, v in r.items()},
         "paper_avg": _paper_cell(_paper(n, i, protocol, args), "Avg")}
        for protocol in PROTOCOLS for (n, i), r in by_protocol[protocol].items()],
        "not_run": [{"method": n, "input": i, "why": w} for (n, i), w in not_run.items()]})
    write_json(out / "meta.json", meta)
    (out / "table1.md").write_text(text + "\n")
    _plot(results, out / "table1.png", args.data)
    written = ["table1.md", "table1.csv", "table1.json", "meta.json", "table1.png"]
    if args.plots:
        written += _figures(out, splits, results, predictions, ctx, args.data, cols)
    print(f"\nwrote {out}/{', '.join(written)} ({total:.0f} s)")
    return 0


def _figures(out: Path, splits, results, predictions, ctx, data: str, cols: list[str]) -> list[str]:
    """The comparison figures of every input type (benchmarks.figures); returns the file names."""
    from benchmarks import figures

    written = []
    for inp, split in splits.items():
        names = [n for (n, i) in results if i == inp]
        if not names:
            continue
        bars = {n: {c: results[(n, inp)].get(c, (np.nan,))[0] for c in cols + ["Avg"]} for n in names}
        paper = {n: {c: _paper_cell(PAPER[(n, inp)], c) for c in cols + ["Avg"]} for n in names
                 if (n, inp) in PAPER and data == "h36m"}
        figures.per_action_bars(out / f"table1_{inp}_actions.png", bars, cols + ["Avg"], paper,
                                title=f"Table 1 ({inp}, {data}): MPJPE per action"
                                + ("; black: the paper" if paper else ""))
        shown = [n for n in ("PRN-FCN",) if n in names]
        shown += [n for n in ("SPM + NN", "CSF2 + NN", "C3DPO", "PR + NN", "GT 3D", "PRN w/o reg") if n in names][:1]
        frames = figures.pick_frames(split.test_truth)
        shapes = figures.shapes_for_frames({n: predictions[(n, inp)] for n in shown}, split.test_truth, frames)
        inputs = np.stack([split.test_inputs[i].points_2d[t] for i, t in frames])
        seq0 = split.test_truth[0]
        figures.qualitative(out / f"table1_{inp}_qualitative.png", inputs, shapes, seq0.edges, seq0.joint_names,
                            title=f"Table 1 ({inp}, {data}): test frames; depth sign as the metric chooses it")
        caches = {k: Path(v["cache"]) for k, v in ctx.timings.items() if k.endswith(f"({inp})") and "cache" in v}
        figures.training_curves(out / f"table1_{inp}_curves.png", caches, title=f"Table 1 ({inp}): training loss")
        written += [f"table1_{inp}_{k}.png" for k in ("actions", "qualitative", "curves")]
    return written


def _paper(name: str, inp: str, protocol: str, args: argparse.Namespace):
    """The paper's numbers of a row in ``protocol``, or None (none published in that protocol, or a validation
    run, whose numbers are not the paper's test numbers)."""
    if args.validate is not None or PAPER_PROTOCOL.get((name, inp)) != protocol:
        return None
    return PAPER[(name, inp)]


def _protocol_rows(protocol: str, inp: str, names: list[str], results: dict, not_run: dict, cols: list[str],
                   args: argparse.Namespace, registry: dict, rows_csv: list[dict]) -> list[list]:
    """The Markdown rows of one input in one protocol (ours, then the paper's numbers measured in that protocol);
    appends the CSV rows to ``rows_csv``."""
    rows = []
    for name in names:
        paper = _paper(name, inp, protocol, args)
        paper_avg = paper[-1] if paper else None
        if (name, inp) in results:
            r = results[(name, inp)]
            rows.append([f"{name} (ours)"] + [r.get(c, (None, 0))[0] for c in cols] + [r["Avg"][0], paper_avg])
            for c in cols + ["Avg"]:
                if c in r:
                    rows_csv.append({"input": inp, "protocol": protocol, "method": name, "action": c,
                                     "mpjpe_mm": r[c][0], "frames": r[c][1], "paper_mpjpe_mm": _paper_cell(paper, c)})
        else:
            why = not_run.get((name, inp), "not run")
            rows.append([f"{name} (ours)"] + ["not run"] * len(cols) + [f"not run: {why}", paper_avg])
        if paper and args.data == "h36m":
            rows.append([f"{name} (paper)"] + [_paper_cell(paper, c) for c in cols] + [paper[-1], paper[-1]])
    for (pname, pinp), paper in PAPER.items():
        if pinp == inp and pname not in names and _paper(pname, pinp, protocol, args):
            why = "not selected with --methods" if pname in registry else "not implemented here yet"
            rows.append([f"{pname} (paper; {why})"]
                        + ([_paper_cell(paper, c) for c in cols] if args.data == "h36m" else [None] * len(cols))
                        + [None, paper[-1]])
    return rows


def _paper_cell(paper, col):
    if paper is None or col not in PAPER_COLUMNS + ("Avg",):
        return None
    return paper[-1] if col == "Avg" else paper[PAPER_COLUMNS.index(col)]


def _plot(results, path: Path, data: str) -> None:
    from benchmarks.figures import pyplot, save

    plt = pyplot()

    labels = [f"{n}\n{i}" for (n, i) in results]
    ours = [r["Avg"][0] for r in results.values()]
    paper = [PAPER.get(k, (np.nan,))[-1] for k in results]
    x = np.arange(len(labels))
    fig, ax = plt.subplots(figsize=(max(4, 1.6 * len(labels)), 3.2))
    ax.bar(x - 0.2, ours, 0.4, label=f"ours ({data})")
    ax.bar(x + 0.2, paper, 0.4, label="paper (Human3.6M)")
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("MPJPE (mm)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    save(fig, path)


if __name__ == "__main__":
    sys.exit(main())
