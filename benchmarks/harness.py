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

from benchmarks.common import (add_training_arguments, choose_data, labels_dir, markdown_table, run_metadata, run_table,
                               write_csv, write_json)
from benchmarks.methods import methods
from benchmarks.registry import (QUICK_LABEL_PARAMS, NotRun, Predictions, RunContext, Split, millimetres,
                                 schedule_text)
from nrsfm.errors import ValidationError

log = logging.getLogger("benchmarks.harness")

#: The suffix of the rows that solve the test data itself (:attr:`TableSpec.direct`).
DIRECT = "on the test data"
#: How a dataset of the paper is named under the table (its numbers are that dataset's).
PAPER_DATA = {"300vw": "300-VW", "h36m": "Human3.6M", "surreal": "SURREAL"}


@dataclass(frozen=True)
class TableSpec:
    """A paper table of one error column.

    Attributes:
        name: output stem and program name (``table3``).
        title: the caption's first words.
        rows: registered method names, in the paper's order.
        paper: published value per row (real data only).
        load: ``load(args) -> (split, description)``, or ``({section: split}, description)`` for a table of
            several sections (a row's error per section: two 2D inputs of the same faces); ``args.data`` is
            ``"synthetic"`` or a real dataset's name. ``description["context"]``, where present, overrides
            ``context`` for that data.
        iterations: default training iterations for (real, synthetic, quick) data.
        metric: the column's name; errors are per frame, frame-weighted means.
        error: ``error(pred, truth) -> (F,)`` on the de-normalised prediction and the ground truth.
        context: extra :class:`RunContext` fields (network width, point groups) on real data;
            synthetic_context: the same for the stand-in (default: ``context``).
        frame: the frame of evaluation, stated under the table.
        images: the rows read images (``rgb`` input): adds ``--backbone`` and ``--image-size``.
        real_data: the real datasets the table reads, (name, dataset folders) in order of priority
            (default: ``real_name`` in a folder of that name).
        bands: ``bands(truth) -> (F,)`` labels of one test sequence's frames (e.g. head yaw bands): each row's
            error is also given per label.
        direct: per-sequence solvers (registry names) also run on the test inputs themselves, each a row
            "<solver> on the test data": what a method that sees every test frame at once makes of them.
        c3dpo_lr: C3DPO's default learning rate in this table.
        validate: ``load`` honours ``--validate`` (a validation part of the training data in place of the test
            data, for choosing settings; no paper numbers beside it).
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
    real_data: tuple[tuple[str, tuple[str, ...]], ...] = ()
    bands: Callable[[object], np.ndarray] | None = None
    band_name: str = "band"
    direct: tuple[str, ...] = ()
    c3dpo_lr: float = 1e-3
    validate: bool = False

    @property
    def datasets(self) -> tuple[tuple[str, tuple[str, ...]], ...]:
        return self.real_data or ((self.real_name, (self.real_name,)),)


def normalized_error(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The paper's NE per frame, ``||X - X*||_F / ||X*||_F``, both centred, the z sign chosen per frame."""
    from nrsfm.metrics import normalized_error_per_frame

    return normalized_error_per_frame(pred, truth)


def evaluate(preds: list[np.ndarray], truth: list, error) -> tuple[float, int]:
    """Frame-weighted mean of ``error`` over the test sequences (predictions scaled back by
    :func:`benchmarks.registry.millimetres`)."""
    e = per_frame(preds, truth, error)
    return float(e.mean()), int(len(e))


def per_frame(preds: list[np.ndarray], truth: list, error) -> np.ndarray:
    """`(N,)` ``error`` of every test frame, the test sequences one after the other."""
    return np.concatenate([error(p, s.points_3d) for p, s in zip(millimetres(preds, truth), truth)])


def by_band(errors: np.ndarray, labels: np.ndarray) -> dict[str, tuple[float, int]]:
    """Mean error and frame count per label (in sorted order)."""
    return {str(b): (float(errors[labels == b].mean()), int((labels == b).sum())) for b in sorted(set(labels))}


def solve_directly(split: Split, solver: str, jobs: int = 1, params: dict | None = None) -> Predictions:
    """``solver`` (an :mod:`nrsfm` registry name, at its defaults but for ``params``) on each test input sequence
    itself: its shapes in the data's units (``millimetres``), and in PRN's per-frame units for the figures."""
    from joblib import Parallel, delayed, parallel_config

    from prn.data import normalize_3d

    with parallel_config(backend="loky", n_jobs=min(jobs, len(split.test_inputs)), inner_max_num_threads=1):
        recs = Parallel()(delayed(_solve)(seq, solver, params or {}) for seq in split.test_inputs)
    out = Predictions(r / normalize_3d(t.points_3d)[1][:, None, None] for r, t in zip(recs, split.test_truth))
    out.millimetres = recs
    return out


def _solve(seq, solver: str, params: dict) -> np.ndarray:
    import nrsfm

    return nrsfm.solve(seq.replace(points_3d=None), solver, **params).points_3d


def parser(spec: TableSpec) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.{spec.name}", description=spec.title)
    names = [n for n, _ in spec.datasets]
    where = ", else ".join(f"{n} when the data folder holds {' and '.join(f + '/' for f in fs)}"
                           for n, fs in spec.datasets)
    p.add_argument("--data", choices=["synthetic", *names], default=None,
                   help=f"default: {where}, else synthetic (the embedded stand-in)")
    p.add_argument("--root", help="data folder (default: $NRSFM_DATA)")
    p.add_argument("--quick", action="store_true", help="a short schedule and small data: a smoke run")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"training iterations (default: {spec.iterations[0]} real as the paper, {spec.iterations[1]} "
                        f"synthetic, {spec.iterations[2]} quick)")
    p.add_argument("--methods", default=None, help=f"comma-separated rows (default: {', '.join(spec.rows)})")
    p.add_argument("--out", default=None, help=f"output folder (default: runs/{spec.name}-<data>)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel pseudo-label solves")
    p.add_argument("--c3dpo-iterations", type=int, default=None, help="C3DPO's iterations (default: scaled)")
    p.add_argument("--c3dpo-batch", type=int, default=None, help="C3DPO's minibatch (default 1024; 128 quick)")
    p.add_argument("--c3dpo-lr", type=float, default=spec.c3dpo_lr,
                   help=f"C3DPO's learning rate before its two drops (default {spec.c3dpo_lr:g})")
    if spec.validate:
        p.add_argument("--validate", action="store_true",
                       help="train on part of the training data and evaluate on the rest of it instead of the test "
                            "data (for choosing a setting; no paper numbers beside it)")
    if spec.direct:
        p.add_argument("--direct", default=",".join(spec.direct),
                       help=f"per-sequence solvers also run on the test inputs themselves, each a row "
                            f"(default: {','.join(spec.direct)}; '' for none)")
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
    return run_table(spec.name, lambda a: run(spec, a), parser(spec).parse_args(argv))


def run(spec: TableSpec, args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    notice = choose_data(args, spec.datasets, spec.name)
    if notice:
        print(notice, flush=True)
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
    if args.jobs < 1 or (args.c3dpo_batch is not None and args.c3dpo_batch < 2):
        raise ValidationError(f"--jobs and --c3dpo-batch: expected >= 1 and >= 2, got {args.jobs}, {args.c3dpo_batch}")
    if getattr(args, "image_size", None) is not None and args.image_size < 16:
        raise ValidationError(f"--image-size: expected at least 16 pixels, got {args.image_size}")
    loaded, desc = spec.load(args)
    sections = loaded if isinstance(loaded, dict) else {"": loaded}
    context = dict(spec.context if real or spec.synthetic_context is None else spec.synthetic_context)
    context.update(desc.get("context", {}))
    if getattr(args, "backbone", None):
        context["network"] = args.backbone
    for option in ("c3dpo_batch", "c3dpo_iterations"):  # given on the command line, they win over the table's
        if getattr(args, option) is not None:
            context[option] = getattr(args, option)
    context.setdefault("c3dpo_batch", 128 if args.quick else 1024)
    if args.quick:  # a smoke run: C3DPO as many iterations as the other rows, unless given
        context["c3dpo_iterations"] = args.c3dpo_iterations or iterations
    ctx = RunContext(out_dir=out, labels_dir=labels_dir(args), iterations=iterations, seed=args.seed,
                     progress=not args.no_progress, device=args.device, retrain=args.retrain, jobs=args.jobs,
                     c3dpo_lr=args.c3dpo_lr,
                     label_params=QUICK_LABEL_PARAMS if args.quick else {},
                     compress_schedule=args.compress_schedule, **context)
    direct = [d.strip() for d in getattr(args, "direct", "").split(",") if d.strip()]
    if not np.isfinite(args.c3dpo_lr) or args.c3dpo_lr <= 0:
        raise ValidationError(f"--c3dpo-lr: expected a learning rate > 0, got {args.c3dpo_lr}")
    from nrsfm.solvers.registry import available_solvers

    for d in direct:
        if d not in available_solvers():
            raise ValidationError(f"--direct: expected solver names among {available_solvers()}, got {d!r}")
    results: dict[tuple[str, str], tuple[float, int]] = {}
    bands: dict[tuple[str, str], dict[str, tuple[float, int]]] = {}
    predictions: dict[tuple[str, str], list[np.ndarray]] = {}
    not_run: dict[tuple[str, str], str] = {}
    for section, split in sections.items():
        log.info("%s: %s%s, %d training and %d test sequences, %d iterations", spec.name, desc.get("data"),
                 f" ({section})" if section else "", len(split.train_inputs), len(split.test_inputs), iterations)
        labels = None if spec.bands is None else np.concatenate([spec.bands(t) for t in split.test_truth])
        if labels is not None and len(set(labels)) < 2:
            labels = None  # one band: nothing to split
        for name in names + [f"{d} {DIRECT}" for d in direct]:
            key = (section, name)
            if name.endswith(DIRECT):
                log.info("%s: solving the test data with %s ...", spec.name, name)
                t0 = time.perf_counter()
                params = ctx.label_params.get(name.removesuffix(f" {DIRECT}"))
                predictions[key] = solve_directly(split, name.removesuffix(f" {DIRECT}"), ctx.jobs, params)
                ctx.timings[f"{name} ({section or split.input_type})"] = {
                    "seconds": time.perf_counter() - t0, "params": params or "defaults"}
            else:
                m = registry[name]
                if split.input_type not in m.inputs:
                    not_run[key] = f"{name} does not take {split.input_type} input"
                    continue
                log.info("%s: training/evaluating %s ...", spec.name, name)
                try:
                    predictions[key] = m.run(split, ctx)
                except NotRun as why:
                    not_run[key] = str(why)
                    continue
                finally:
                    if section and f"{name} ({split.input_type})" in ctx.timings:  # one entry per section
                        ctx.timings[f"{name} ({section})"] = ctx.timings.pop(f"{name} ({split.input_type})")
            errors = per_frame(predictions[key], split.test_truth, spec.error)
            results[key] = (float(errors.mean()), int(len(errors)))
            if labels is not None:
                bands[key] = by_band(errors, labels)

    if getattr(args, "validate", False):
        real = False  # validation numbers: not the paper's test numbers
    paper_on = spec.real_name if real and args.data != spec.real_name else None  # the paper's are another set's
    paper_head = f"{spec.metric} (paper{', ' + PAPER_DATA.get(spec.real_name, spec.real_name) if paper_on else ''})"
    evaluated = f", evaluated on the {desc['evaluated']}" if desc.get("evaluated") else ""
    text = (f"### {spec.title}: {spec.metric}, {desc.get('data')}{evaluated}, {iterations:,} iterations, "
            f"{schedule_text(iterations, args.compress_schedule)}, {spec.frame}\n")
    all_rows = names + [f"{d} {DIRECT}" for d in direct]
    for section in sections:
        rows = []
        for name in all_rows:
            key = (section, name)
            ours = results[key][0] if key in results else f"not run: {not_run[key]}"
            rows.append([name, ours, spec.paper.get(name) if real else None])
        for name, value in spec.paper.items():
            if name not in names:
                rows.append([f"{name} (paper; not selected with --methods)", None, value if real else None])
        if section:
            text += f"\n#### {section}\n"
        text += "\n" + markdown_table(["Method", f"{spec.metric} (ours)", paper_head], rows) + "\n"
        if bands:
            cols = sorted({b for (sec, _), per in bands.items() if sec == section for b in per})
            counts = {b: next(per[b][1] for (sec, _), per in bands.items() if sec == section and b in per)
                      for b in cols}
            text += (f"\n{spec.metric} per {spec.band_name} ({section or 'test'}):\n\n"
                     + markdown_table(["Method"] + [f"{b} ({counts[b]})" for b in cols],
                                      [[name] + [bands[(section, name)].get(b, (None,))[0] for b in cols]
                                       for name in all_rows if (section, name) in bands]) + "\n")
    if direct:
        text += (f"\nRows \"{DIRECT}\": the per-sequence solver run on the test inputs themselves (it sees every "
                 "test frame at once; the networks see one frame).\n")
    if split.input_type == "rgb":
        from prn.images import initialisation

        context["initialisation"] = initialisation(context.get("network", ctx.network))
        text += f"\nImages: {desc.get('images')}; network: {context['initialisation']}.\n"
    labels_used = [(k, v["labels"]) for k, v in ctx.timings.items() if "labels" in v]
    if labels_used:
        text += "\nPseudo-labels (training frames; the labels' own error is in the JSON):\n\n" + \
            markdown_table(["row", "solver", "cuts", "failed", "labelled frames", "seconds"],
                           [[k, s["method"], s["cuts"], s["failed"], f"{s['labelled_frames']} of {s['frames']}",
                             s["seconds"]] for k, s in labels_used]) + "\n"
    if notice:
        text = notice + "; the paper's numbers are left out.\n\n" + text
    print(text)
    total = time.perf_counter() - t_start
    meta = run_metadata(table=f"PRN {spec.title}", metric=spec.metric, data=desc, methods=names, direct=direct,
                        iterations=iterations, schedule=schedule_text(iterations, args.compress_schedule),
                        seed=args.seed, quick=args.quick, context=context, timings=ctx.timings, total_seconds=total)
    flat = [{"section": sec, "method": n, "error": v[0], "frames": v[1],
             "paper": spec.paper.get(n) if real else None, "paper_data": paper_on or (spec.real_name if real else None),
             "bands": {b: {"error": e, "frames": f} for b, (e, f) in bands.get((sec, n), {}).items()}}
            for (sec, n), v in results.items()]
    write_csv(out / f"{spec.name}.csv", [{"section": r["section"], "method": r["method"], "band": "all",
                                          "error": r["error"], "frames": r["frames"], "metric": spec.metric,
                                          "paper": r["paper"]} for r in flat]
              + [{"section": r["section"], "method": r["method"], "band": b, "error": v["error"],
                  "frames": v["frames"], "metric": spec.metric, "paper": None} for r in flat
                 for b, v in r["bands"].items()])
    write_json(out / f"{spec.name}.json", {"meta": meta, "results": flat, "paper": spec.paper,
                                           "not_run": [{"section": sec, "method": n, "why": w}
                                                       for (sec, n), w in not_run.items()]})
    write_json(out / "meta.json", meta)
    (out / f"{spec.name}.md").write_text(text + "\n")
    bar_chart(results, spec.paper if real else {}, out / f"{spec.name}.png", spec.metric,
              f"{spec.title} ({desc.get('data')})", paper_label=paper_head.removeprefix(spec.metric + " ").strip("()"))
    written = f"{spec.name}.md, .csv, .json, meta.json, .png"
    if args.plots and results:
        from benchmarks import figures

        for section, split in sections.items():
            found = {n for (sec, n) in results if sec == section}
            shown = [n for n in ("PRN-FCN", "PRN-CNN", "C3DPO", "PR + NN", "SPM + CNN", "PR + CNN", "CSF2 + NN",
                                 "CSF2 + CNN", "PRN w/o reg", "GT 3D") if n in found][:3]
            frames = figures.pick_frames(split.test_truth)
            shapes = figures.shapes_for_frames({n: predictions[(section, n)] for n in shown}, split.test_truth, frames)
            seq = split.test_truth[0]
            images = None if split.test_images is None else np.stack([split.test_images[i][np.array([t])][0]
                                                                      for i, t in frames])
            stem = f"{spec.name}{'_' + section if section else ''}"
            figures.qualitative(out / f"{stem}_qualitative.png",
                                np.stack([split.test_inputs[i].points_2d[t] for i, t in frames]), shapes, seq.edges,
                                seq.joint_names, title=f"{spec.title} ({desc.get('data')}{', ' + section if section else ''}): "
                                "test frames", images=images)
            written += f", {stem}_qualitative.png"
        figures.training_curves(out / f"{spec.name}_curves.png", {k: Path(v["cache"]) for k, v in ctx.timings.items()
                                                                 if "cache" in v}, title=f"{spec.title}: training loss")
        written += f", {spec.name}_curves.png"
    print(f"\nwrote {out}/{written} ({total:.0f} s)")
    return 0


def bar_chart(results: dict[tuple[str, str], tuple[float, int]], paper: dict[str, float], path: Path, metric: str,
              title: str, paper_label: str = "paper") -> None:
    """One bar per row and section, the paper's values as markers."""
    from benchmarks.figures import pyplot, save

    plt = pyplot()

    names = list(dict.fromkeys(n for _, n in results))
    sections = list(dict.fromkeys(s for s, _ in results))
    x = np.arange(len(names))
    width = 0.8 / len(sections)
    fig, ax = plt.subplots(figsize=(max(4, 1.3 * len(names)), 3.4))
    for i, sec in enumerate(sections):
        ax.bar(x + (i - (len(sections) - 1) / 2) * width, [results.get((sec, n), (np.nan,))[0] for n in names],
               width, label=f"ours{', ' + sec if sec else ''}")
    if paper:
        ax.plot(x, [paper.get(n, np.nan) for n in names], "k_", markersize=22, mew=2, label=paper_label)
    ax.set_xticks(x, names, fontsize=7, rotation=20, ha="right")
    ax.set_ylabel(metric)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save(fig, path)
