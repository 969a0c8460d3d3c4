"""PRN paper, supplementary Table S1: PRN-FCN's MPJPE (mm) on Human3.6M (GT-ortho) with 0-20% of the 2D points
missing in training and test.

    python -m benchmarks.table_s1 [--data synthetic|h36m] [--root DIR] [--ratios 0,0.05,0.1,0.15,0.2]
                                  [--methods PRN-FCN[,PRN w/o reg][,GT 3D]] [--variants visible[,hidden]]
                                  [--iterations N] [--compress-schedule] [--quick] [--out DIR]
                                  [--missing-in input-and-loss|input] [--resume | --retrain]

The supplementary material's protocol: every point goes missing at random with the given probability, in
training (each sample draws its own points: 0 in the input, weight 0 in the data term; ``TrainConfig.
missing_points``) and in test (a fixed draw per sequence, :func:`nrsfm.datasets.synthetic.drop_entries`, so
every method and run sees the same test points).

Two ways to normalise a frame with missing points (``--variants``), each a row of its own model:

* ``visible`` (the default row): every training sample and every test frame is centred and scaled on its visible
  points alone (:func:`prn.data.normalize_2d`, ``TrainConfig.missing_normalise``), as a user's frames with
  missing detections must be; the prediction is scaled back by the ground truth's same statistic over those
  points. The hidden points' 2D is used nowhere but in the ground truth.
* ``hidden``: centred and scaled on all its points, the hidden ones included, which are then set to 0, as a
  preprocessed dataset would be: the hidden points' true 2D enters through the normalisation.

``--missing-in input`` reads the protocol another way: a training sample's dropped points are 0 in the input only
and the data term keeps their ground-truth 2D, as the paper's networks on Stacked Hourglass detections are trained
against ground-truth 2D.

The error is the PRN protocol's MPJPE over all 17 joints, the missing ones included (the network predicts every
joint). A second table splits it into the joints visible in the input and the missing ones (:func:`by_visibility`)
and gives each model's error on the complete test inputs (points missing in training only). The ``GT 3D`` row
(the same network supervised with ground-truth 3D, its inputs missing the same share of points) bounds what a
single-frame network can make of a missing joint. Data, splits, rows and the cache of trained models are those of
:mod:`benchmarks.table1`; one model is trained per row, variant and ratio.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import (add_training_arguments, choose_data, markdown_table, parse_fractions, run_metadata,
                               run_table, write_csv, write_json)
from benchmarks.methods import methods
from benchmarks.registry import Predictions, RunContext, Split, millimetres, schedule_text
from benchmarks.table1 import evaluate, load_splits
from nrsfm.datasets.synthetic import drop_entries
from nrsfm.errors import ValidationError

log = logging.getLogger("benchmarks.table_s1")

RATIOS = (0.0, 0.05, 0.1, 0.15, 0.2)
#: ``--variants``: where a frame with missing points is normalised, and how its row is labelled.
VARIANTS = {"visible": "normalised on its visible points",
            "hidden": "normalised with the hidden points, as a preprocessed dataset would be"}
#: Published numbers (PRN, ECCV 2020, supplementary Table 1): Avg MPJPE (mm) per missing ratio.
PAPER = {"PRN-FCN": dict(zip(RATIOS, (66.7, 69.8, 70.8, 72.1, 73.8)))}
ROWS = ("PRN-FCN", "PRN w/o reg", "GT 3D")


def missing_split(split: Split, ratio: float) -> Split:
    """``split`` with ``ratio`` of the test entries marked missing (the same entries in every run)."""
    return Split(split.train_inputs, split.train_targets, [drop_entries(s, ratio) for s in split.test_inputs],
                 split.test_truth, split.input_type, split.sampling, split.tag)


def by_visibility(preds: list[np.ndarray], split: Split) -> dict[str, float | None]:
    """Mean joint errors (mm) split by the input's visibility: ``visible`` and ``missing`` in the frame of the
    PRN protocol's MPJPE (each frame centred and its z sign chosen on all its joints), and ``visible_alone``, the
    visible joints measured without the missing ones (each frame centred and its z sign chosen on its visible
    joints only)."""
    from nrsfm.metrics import mpjpe_prn_per_joint

    errs, vis, alone = [], [], []
    for pred, s, t in zip(millimetres(preds, split.test_truth), split.test_inputs, split.test_truth):
        gt = t.points_3d
        errs.append(mpjpe_prn_per_joint(pred, gt))
        vis.append(s.weights > 0)
        alone.append(_visible_alone(pred, gt, vis[-1]))
    e, v, a = np.concatenate(errs), np.concatenate(vis), np.concatenate(alone)
    return {"visible": float(e[v].mean()) if v.any() else None, "missing": float(e[~v].mean()) if (~v).any() else None,
            "visible_alone": float(a[v].mean()) if v.any() else None}


def _visible_alone(pred: np.ndarray, gt: np.ndarray, vis: np.ndarray) -> np.ndarray:
    """`(F, P)` joint errors of `(F, P, 3)` ``pred`` against ``gt`` with each frame centred on its visible joints
    ``vis`` `(F, P)` and its z sign chosen on them (the missing joints' entries are meaningless)."""
    w = vis[..., None].astype(float)
    n = np.maximum(w.sum(axis=1, keepdims=True), 1.0)
    pc = pred - (pred * w).sum(axis=1, keepdims=True) / n
    gc = gt - (gt * w).sum(axis=1, keepdims=True) / n
    flipped = pc * np.array([1.0, 1.0, -1.0])
    keep = (((pc - gc) ** 2 * w).sum(axis=(1, 2)) <= ((flipped - gc) ** 2 * w).sum(axis=(1, 2)))
    return np.linalg.norm(np.where(keep[:, None, None], pc, flipped) - gc, axis=2)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.table_s1", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", choices=["synthetic", "h36m"], default=None,
                   help="default: h36m when the data folder holds h36m/, else the embedded synthetic stand-in")
    p.add_argument("--root", help="data folder holding h36m/ (default: $NRSFM_DATA)")
    p.add_argument("--ratios", default=",".join(str(r) for r in RATIOS), help="missing ratios (default: the paper's)")
    p.add_argument("--methods", default="PRN-FCN", help=f"comma-separated rows among {ROWS} (default: PRN-FCN, "
                                                          "the paper's only row)")
    p.add_argument("--variants", default=",".join(VARIANTS),
                   help="where frames with missing points are normalised, a row each: visible (on their visible "
                        "points alone, as a user's detections must be) and hidden (on all points, the hidden ones "
                        "included, as a preprocessed dataset would be); default: both")
    p.add_argument("--quick", action="store_true", help="a short schedule and small data: a smoke run")
    p.add_argument("--iterations", type=int, default=None,
                   help="training iterations (default: 70000 for h36m as the paper, 4000 synthetic, 300 quick)")
    p.add_argument("--out", default=None, help="output folder (default: runs/table_s1-<data>)")
    p.add_argument("--missing-in", choices=["input-and-loss", "input"], default="input-and-loss",
                   help="where a training sample's dropped points go missing: the input and the data term "
                        "(default), or the input only (the data term keeps their ground-truth 2D)")
    p.add_argument("--stride", default="auto", help="Human3.6M frame stride: 5 for 50 fps files, 1 for 10 fps copies")
    add_training_arguments(p)
    args = p.parse_args(argv)
    return run_table("table_s1", _run, args)


def _run(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    notice = choose_data(args, [("h36m", ("h36m",))], "table_s1")
    if notice:
        print(notice, flush=True)
    ratios = tuple(parse_fractions(args.ratios, "--ratios"))
    names = [m.strip() for m in args.methods.split(",")]
    for n in names:
        if n not in ROWS:
            raise ValidationError(f"--methods: expected names among {list(ROWS)}, got {n!r}")
    variants = [v.strip() for v in args.variants.split(",")]
    for v in variants:
        if v not in VARIANTS:
            raise ValidationError(f"--variants: expected names among {list(VARIANTS)}, got {v!r}")
    if args.iterations is not None and args.iterations < 1:
        raise ValidationError(f"--iterations: expected a number of training iterations >= 1, got {args.iterations}")
    iterations = args.iterations or (300 if args.quick else 70_000 if args.data == "h36m" else 4000)
    out = Path(args.out or f"runs/table_s1-{args.data}{'-quick' if args.quick else ''}")
    registry = methods()
    splits, desc = load_splits(args, ("gt-ortho",))
    split = splits["gt-ortho"]
    rows_of = [(name, variant) for name in names for variant in variants]
    results: dict[tuple[str, str, float], dict[str, tuple[float, int]]] = {}
    split_errors: dict[tuple[str, str, float], dict[str, float | None]] = {}
    timings: dict = {}
    for ratio in ratios:
        test = missing_split(split, ratio)
        n = len(test.test_inputs)
        # one run predicts the test sequences with their points missing, then complete (ratio > 0)
        both = test if ratio == 0 else dataclasses.replace(
            test, test_inputs=test.test_inputs + split.test_inputs, test_truth=test.test_truth + split.test_truth)
        for name, variant in rows_of:
            if ratio == 0 and variant != variants[0]:  # nothing is missing: one model serves every variant
                results[(name, variant, ratio)] = results[(name, variants[0], ratio)]
                split_errors[(name, variant, ratio)] = split_errors[(name, variants[0], ratio)]
                continue
            ctx = RunContext(out_dir=out, iterations=iterations, seed=args.seed, progress=not args.no_progress,
                             device=args.device, retrain=args.retrain, missing_points=ratio,
                             missing_in_loss=args.missing_in == "input-and-loss", compress_schedule=args.compress_schedule,
                             normalise_on="visible" if variant == "visible" else "all")
            log.info("table_s1: %s (%s) with %.0f%% of the points missing ...", name, variant, 100 * ratio)
            out_preds = registry[name].run(both, ctx)
            mm = millimetres(out_preds, both.test_truth)
            preds = Predictions(out_preds[:n])
            preds.millimetres = mm[:n]
            results[(name, variant, ratio)] = evaluate(preds, test.test_truth)
            split_errors[(name, variant, ratio)] = by_visibility(preds, test)
            complete = Predictions(out_preds[n:] if ratio > 0 else out_preds)
            complete.millimetres = mm[n:] if ratio > 0 else mm
            split_errors[(name, variant, ratio)]["test_complete"] = evaluate(complete, split.test_truth)["Avg"][0]
            timings[f"{name}, {variant}, {ratio}"] = ctx.timings

    def label(name, variant):
        return f"{name} ({'ours' if len(variants) == 1 or variant == 'visible' else 'ours; ' + VARIANTS[variant]})"

    header = ["Method"] + [f"{100 * r:g}%" for r in ratios]
    rows, rows_csv = [], []
    for name, variant in rows_of:
        rows.append([label(name, variant)] + [results[(name, variant, r)]["Avg"][0] for r in ratios])
        for r in ratios:
            for action, (err, frames) in results[(name, variant, r)].items():
                rows_csv.append({"method": name, "variant": variant, "missing_ratio": r, "action": action,
                                 "mpjpe_mm": err, "frames": frames,
                                 "paper_mpjpe_mm": PAPER.get(name, {}).get(r) if action == "Avg"
                                 and args.data == "h36m" else None})
    for name in names:
        if name in PAPER and args.data == "h36m":
            rows.append([f"{name} (paper)"] + [PAPER[name].get(r) for r in ratios])
    text = (f"### Table S1: MPJPE (mm) with missing 2D points in training and test, {desc['data']} GT-ortho, test "
            f"{'+'.join(desc['test_subjects'])}, {iterations:,} iterations, "
            f"{schedule_text(iterations, args.compress_schedule)}, training points missing from the "
            f"{args.missing_in.replace('-', ' ')}; rows: "
            + "; ".join(f"{v}: every training sample and test frame {VARIANTS[v]}" for v in variants)
            + "; PRN protocol (mean-centred, z sign per frame, no Procrustes; all joints, missing ones included)\n\n"
            + markdown_table(header, rows))
    parts = {"visible": "visible joints", "missing": "missing joints",
             "visible_alone": "visible joints, centred and z-signed on them alone",
             "test_complete": "all joints, the test inputs complete (points missing in training only)"}
    vis_rows = [[f"{name}, {variant}: {label_}"] + [split_errors[(name, variant, r)][part] for r in ratios]
                for name, variant in rows_of for part, label_ in parts.items()]
    text += ("\n\nThe same errors over the joints visible in the input and over the missing ones (mm); the third "
             "row leaves the missing joints out of the centring and z sign too; the last is the same model's error "
             "when no test point is missing:\n\n" + markdown_table(header, vis_rows))
    if notice:
        text = notice + "; the paper's numbers are Human3.6M's and are not shown beside it.\n\n" + text
    print(text)
    total = time.perf_counter() - t_start
    meta = run_metadata(table="PRN supplementary Table S1", metric="MPJPE (mm), PRN protocol", data=desc,
                        ratios=list(ratios), variants={v: VARIANTS[v] for v in variants}, missing_in=args.missing_in,
                        methods=names, iterations=iterations, schedule=schedule_text(iterations, args.compress_schedule),
                        seed=args.seed, quick=args.quick, timings=timings, total_seconds=total)
    write_csv(out / "table_s1.csv", rows_csv)
    write_json(out / "table_s1.json", {"meta": meta, "results": [
        {"method": n, "variant": v, "missing_ratio": r,
         "per_action": {a: {"mpjpe_mm": e[0], "frames": e[1]} for a, e in res.items()},
         "paper_avg": PAPER.get(n, {}).get(r), "mpjpe_by_visibility_mm": split_errors[(n, v, r)]}
        for (n, v, r), res in results.items()]})
    write_json(out / "meta.json", meta)
    (out / "table_s1.md").write_text(text + "\n")
    _plot(results, rows_of, ratios, out / "table_s1.png", args.data, label)
    print(f"\nwrote {out}/table_s1.md, table_s1.csv, table_s1.json, meta.json, table_s1.png ({total:.0f} s)")
    return 0


def _plot(results, rows_of, ratios, path: Path, data: str, label) -> None:
    from benchmarks.figures import pyplot, save

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    x = 100 * np.asarray(ratios)
    for name, variant in rows_of:
        ax.plot(x, [results[(name, variant, r)]["Avg"][0] for r in ratios], "o-", label=f"{label(name, variant)}, "
                f"{data}")
    for name in dict.fromkeys(n for n, _ in rows_of):
        if name in PAPER and data == "h36m":
            ax.plot(x, [PAPER[name].get(r, np.nan) for r in ratios], "x--", label=f"{name} (paper)")
    ax.set_xlabel("missing points (%)")
    ax.set_ylabel("MPJPE (mm)")
    ax.set_title("Table S1: missing 2D points", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save(fig, path)


if __name__ == "__main__":
    sys.exit(main())
