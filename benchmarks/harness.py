"""One harness for the tables whose cell is one number per row (the PRN paper's Tables 3 and 4: normalised error).

A table is a :class:`TableSpec`: its rows (registered methods, :mod:`benchmarks.registry`), the paper's numbers,
how to load the real data and the embedded stand-in, and the network options the paper states for it. The
harness parses the common options, trains and evaluates every row on the same split, prints the table beside the
paper's numbers, and writes ``<name>.md``, ``.csv``, ``.json``, ``meta.json`` and a bar chart ``<name>.png``;
trained models are cached by configuration (``--resume``, the default, reuses them and resumes interrupted
training).
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.common import (add_training_arguments, labels_dir, markdown_table, run_metadata, run_table, write_csv,
                               write_json)
from benchmarks.registry import QUICK_LABEL_PARAMS, RunContext, Split, methods
from nrsfm.errors import ValidationError

log = logging.getLogger("benchmarks.harness")


@dataclass(frozen=True)
class TableSpec:
    """A paper table of one error column.

    Attributes:
        name: output stem and program name (``table3``).
        title: the caption's first words.
        rows: registered method names, in the paper's order.
        paper: published value per row (real data only).
        load: ``load(args) -> (split, description)``; ``args.data`` is ``"real"`` or ``"synthetic"``.
        iterations: default training iterations for (real, synthetic, quick) data.
        metric: the column's name; errors are per frame, frame-weighted means.
        error: ``error(pred, truth) -> (F,)`` on the de-normalised prediction and the ground truth.
        context: extra :class:`RunContext` fields (network width, point groups) on real data;
            synthetic_context: the same for the stand-in (default: ``context``).
        frame: the frame of evaluation, stated under the table.
        images: the rows read images (``rgb`` input): adds ``--backbone`` and ``--image-size``.
    """

    name: str
    title: str
    rows: tuple[str, ...]
    paper: dict[str, float]
    load: Callable[[argparse.Namespace], tuple[Split, dict]]
    iterations: tuple[int, int, int]
    metric: str
    error: Callable[[np.ndarray, np.ndarray], np.ndarray]
    frame: str
    context: dict = field(default_factory=dict)
    synthetic_context: dict | None = None
    real_name: str = "real"
    images: bool = False


def normalized_error(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The paper's NE per frame, ``||X - X*||_F / ||X*||_F``, both centred, the z sign chosen per frame."""
    from nrsfm.metrics import normalized_error_per_frame

    return normalized_error_per_frame(pred, truth)


def evaluate(preds: list[np.ndarray], truth: list, error) -> tuple[float, int]:
    """Frame-weighted mean of ``error`` over the test sequences (predictions scaled back as the PRN protocol)."""
    from prn.data import denormalize

    errs = [error(denormalize(p, s.points_3d), s.points_3d) for p, s in zip(preds, truth)]
    e = np.concatenate(errs)
    return float(e.mean()), int(len(e))


def parser(spec: TableSpec) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.{spec.name}", description=spec.title)
    p.add_argument("--data", choices=["synthetic", spec.real_name], default=None,
                   help=f"default: {spec.real_name} when --root is given, else synthetic (the embedded stand-in)")
    p.add_argument("--root", help=f"data folder (default: $NRSFM_DATA); implies --data {spec.real_name}")
    p.add_argument("--quick", action="store_true", help="a short schedule and small data: a smoke run")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"training iterations (default: {spec.iterations[0]} real as the paper, {spec.iterations[1]} "
                        f"synthetic, {spec.iterations[2]} quick); the lr schedule is compressed proportionally")
    p.add_argument("--methods", default=None, help=f"comma-separated rows (default: {', '.join(spec.rows)})")
    p.add_argument("--out", default=None, help=f"output folder (default: runs/{spec.name}-<data>)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel pseudo-label solves")
    p.add_argument("--c3dpo-iterations", type=int, default=None, help="C3DPO's iterations (default: scaled)")
    p.add_argument("--c3dpo-batch", type=int, default=None, help="C3DPO's minibatch (default 1024; 128 quick)")
    p.add_argument("--plots", action="store_true", help="also write the qualitative figure and training curves")
    if spec.images:
        from prn.images import BACKBONES

        p.add_argument("--backbone", choices=BACKBONES, default=None,
                       help=f"the CNN's backbone (default: {spec.context.get('network')} real, "
                            f"{(spec.synthetic_context or spec.context).get('network')} synthetic)")
        p.add_argument("--image-size", type=int, default=None, help="image side in pixels (default: 224 real, "
                                                                     "64 synthetic)")
    add_training_arguments(p)
    return p


def main(spec: TableSpec, argv: list[str] | None = None) -> int:
    args = parser(spec).parse_args(argv)
    if args.data is None:
        args.data = spec.real_name if args.root else "synthetic"
    return run_table(spec.name, lambda a: run(spec, a), args)


def run(spec: TableSpec, args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    registry = methods()
    names = list(spec.rows) if args.methods is None else [m.strip() for m in args.methods.split(",")]
    for n in names:
        if n not in registry:
            raise ValidationError(f"--methods: expected names among {list(registry)}, got {n!r}")
    if args.iterations is not None and args.iterations < 1:
        raise ValidationError(f"--iterations: expected a number of training iterations >= 1, got {args.iterations}")
    real = args.data != "synthetic"
    iterations = args.iterations or (spec.iterations[2] if args.quick else spec.iterations[0] if real
                                     else spec.iterations[1])
    out = Path(args.out or f"runs/{spec.name}-{args.data}{'-quick' if args.quick else ''}")
    batch = args.c3dpo_batch or (128 if args.quick else 1024)
    if args.jobs < 1 or batch < 2:
        raise ValidationError(f"--jobs and --c3dpo-batch: expected >= 1 and >= 2, got {args.jobs}, {batch}")
    context = dict(spec.context if real or spec.synthetic_context is None else spec.synthetic_context)
    if getattr(args, "backbone", None):
        context["network"] = args.backbone
    if getattr(args, "image_size", None) is not None and args.image_size < 16:
        raise ValidationError(f"--image-size: expected at least 16 pixels, got {args.image_size}")
    ctx = RunContext(out_dir=out, labels_dir=labels_dir(args), iterations=iterations, seed=args.seed,
                     progress=not args.no_progress, device=args.device, retrain=args.retrain, jobs=args.jobs,
                     c3dpo_batch=batch, c3dpo_iterations=args.c3dpo_iterations,
                     label_params=QUICK_LABEL_PARAMS if args.quick else {}, **context)
    split, desc = spec.load(args)
    log.info("%s: %s, %d training and %d test sequences, %d iterations", spec.name, desc.get("data"),
             len(split.train_inputs), len(split.test_inputs), iterations)
    results: dict[str, tuple[float, int]] = {}
    predictions: dict[str, list[np.ndarray]] = {}
    not_run: dict[str, str] = {}
    for name in names:
        m = registry[name]
        if split.input_type not in m.inputs:
            not_run[name] = f"{name} does not take {split.input_type} input"
            continue
        log.info("%s: training/evaluating %s ...", spec.name, name)
        predictions[name] = m.run(split, ctx)
        results[name] = evaluate(predictions[name], split.test_truth, spec.error)

    rows = []
    for name in names:
        ours = results[name][0] if name in results else f"not run: {not_run[name]}"
        rows.append([name, ours, spec.paper.get(name) if real else None])
    for name, value in spec.paper.items():
        if name not in names:
            rows.append([f"{name} (paper; not selected with --methods)", None, value if real else None])
    text = (f"### {spec.title}: {spec.metric}, {desc.get('data')}, {iterations} iterations, {spec.frame}\n\n"
            + markdown_table(["Method", f"{spec.metric} (ours)", f"{spec.metric} (paper)"], rows))
    if split.input_type == "rgb":
        from prn.images import initialisation

        context["initialisation"] = initialisation(context.get("network", ctx.network))
        text += f"\n\nImages: {desc.get('images')}; network: {context['initialisation']}."
    labels = [(k, v["labels"]) for k, v in ctx.timings.items() if "labels" in v]
    if labels:
        text += "\n\nPseudo-labels (training frames; MPJPE-style error of the labels is in the JSON):\n\n" + \
            markdown_table(["row", "solver", "cuts", "failed", "labelled frames", "seconds"],
                           [[k, s["method"], s["cuts"], s["failed"], f"{s['labelled_frames']} of {s['frames']}",
                             s["seconds"]] for k, s in labels])
    if not real:
        text += "\n\nSynthetic stand-in: not comparable with the paper's numbers, which are left out."
    print(text)
    total = time.perf_counter() - t_start
    meta = run_metadata(table=f"PRN {spec.title}", metric=spec.metric, data=desc, methods=names,
                        iterations=iterations, seed=args.seed, quick=args.quick, context=context,
                        timings=ctx.timings, total_seconds=total)
    write_csv(out / f"{spec.name}.csv", [{"method": n, "error": v[0], "frames": v[1], "metric": spec.metric,
                                          "paper": spec.paper.get(n) if real else None} for n, v in results.items()])
    write_json(out / f"{spec.name}.json", {"meta": meta, "results": {n: {"error": v[0], "frames": v[1]}
                                                                      for n, v in results.items()},
                                           "paper": spec.paper, "not_run": not_run})
    write_json(out / "meta.json", meta)
    (out / f"{spec.name}.md").write_text(text + "\n")
    bar_chart(results, spec.paper if real else {}, out / f"{spec.name}.png", spec.metric,
              f"{spec.title} ({desc.get('data')})")
    written = f"{spec.name}.md, .csv, .json, meta.json, .png"
    if args.plots and results:
        from benchmarks import figures

        shown = [n for n in ("PRN-FCN", "PRN-CNN", "C3DPO", "PR + NN", "SPM + CNN", "PR + CNN", "CSF2 + NN",
                             "CSF2 + CNN", "PRN w/o reg") if n in results][:2]  # PRN and the best baseline
        frames = figures.pick_frames(split.test_truth)
        shapes = figures.shapes_for_frames({n: predictions[n] for n in shown}, split.test_truth, frames)
        seq = split.test_truth[0]
        images = None if split.test_images is None else np.stack([split.test_images[i][np.array([t])][0]
                                                                  for i, t in frames])
        figures.qualitative(out / f"{spec.name}_qualitative.png",
                            np.stack([split.test_inputs[i].points_2d[t] for i, t in frames]), shapes, seq.edges,
                            seq.joint_names, title=f"{spec.title} ({desc.get('data')}): test frames", images=images)
        figures.training_curves(out / f"{spec.name}_curves.png", {k: Path(v["cache"]) for k, v in ctx.timings.items()
                                                                 if "cache" in v}, title=f"{spec.title}: training loss")
        written += f", {spec.name}_qualitative.png, {spec.name}_curves.png"
    print(f"\nwrote {out}/{written} ({total:.0f} s)")
    return 0


def bar_chart(results: dict[str, tuple[float, int]], paper: dict[str, float], path: Path, metric: str,
              title: str) -> None:
    """One bar per row, the paper's values as markers."""
    from benchmarks.figures import pyplot, save

    plt = pyplot()

    names = list(results)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(4, 1.3 * len(names)), 3.2))
    ax.bar(x, [results[n][0] for n in names], 0.6, label="ours")
    if paper:
        ax.plot(x, [paper.get(n, np.nan) for n in names], "k_", markersize=22, mew=2, label="paper")
    ax.set_xticks(x, names, fontsize=7, rotation=15)
    ax.set_ylabel(metric)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save(fig, path)
