"""Pseudo-label quality and cost per solver, on a sample of Human3.6M's training cuts: the study behind PRN-L's
label solver.

    python -m benchmarks.studies.label_quality [--root DIR] [--methods pr:max_iter=200,pr,empnd,consensus]
                                               [--subjects S1] [--every 10] [--input gt-ortho] [--unit-frames]
                                               [--jobs 2] [--out DIR]

The training recordings of ``--subjects`` are cut as the "+NN" rows cut them (:func:`baselines.labels.
multiview_cuts`); every ``--every``-th cut is solved by each solver (``name`` or ``name:param=value``, at its
defaults otherwise), the cuts mirrored to one handedness without ground truth, and each solver's labels scored
against the ground truth with the PRN protocol (MPJPE, mm, as the network learns them: each frame normalised by
its own xy norm and scaled by the ground truth's). The cost is the mean solve time of a cut on one thread,
extrapolated to every cut of ``--subjects`` on 2 cores. No choice here reads the test subjects.

``--unit-frames`` centres each frame's 2D and divides it by its xy norm before the solve: weak-perspective tracks
(GT-persp, SH) change scale with each frame's depth and camera, which an orthographic solver reads as deformation.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import markdown_table, run_metadata, run_table, write_json

def parse_method(text: str) -> tuple[str, dict]:
    """``"pr:max_iter=200"`` -> ("pr", {"max_iter": 200}) with the solver's typed parameters."""
    from nrsfm.solvers.registry import get_solver, params_from_strings

    name, _, rest = text.partition(":")
    assignments = [a for a in rest.split(";") if a] if rest else []
    params = params_from_strings(get_solver(name).params, assignments)
    return name, {a.split("=", 1)[0]: getattr(params, a.split("=", 1)[0]) for a in assignments}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.label_quality", description=__doc__.split("\n\n")[0])
    p.add_argument("--root", help="data folder holding h36m/ (default: $NRSFM_DATA)")
    p.add_argument("--methods", default="pr:max_iter=200,pr,empnd,consensus",
                   help="comma-separated solvers, each NAME or NAME:PARAM=VALUE (;-separated)")
    p.add_argument("--subjects", default="S1", help="training subjects whose cuts are sampled (default S1)")
    p.add_argument("--every", type=int, default=10, help="solve every N-th cut (default 10)")
    p.add_argument("--input", choices=["gt-ortho", "gt-persp", "sh"], default="gt-ortho")
    p.add_argument("--unit-frames", action="store_true",
                   help="centre each frame's 2D and scale it to a unit xy norm before solving")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", default="runs/label_quality")
    p.add_argument("--no-progress", action="store_true")
    return run_table("label_quality", _run, p.parse_args(argv))


def _run(args: argparse.Namespace) -> int:
    from baselines.labels import _MIRROR, _cache_folder, _cut_path, multiview_cuts, resolve_reflections, solve_cuts
    from baselines.labels import label_errors_per_frame
    from nrsfm.datasets import find_dataset, h36m
    from nrsfm.errors import ValidationError
    from nrsfm.io import read_npz
    from prn.data import unit_frames

    if args.every < 1:
        raise ValidationError(f"--every: expected an integer >= 1, got {args.every}")
    root = find_dataset("h36m", args.root)
    subjects = [s.strip() for s in args.subjects.split(",")]
    bad = [s for s in subjects if s not in h36m.TRAIN_SUBJECTS]
    if bad:
        raise ValidationError(f"--subjects: expected training subjects among {h36m.TRAIN_SUBJECTS}, got {bad}")
    stride = h36m.detect_stride(root, subjects[0])
    seqs = h36m.load_h36m(root, subjects, input=args.input, stride=stride, source_fps=50.0)
    truth = h36m.load_h36m(root, subjects, input="gt-persp", stride=stride, source_fps=50.0) \
        if args.input == "sh" else seqs
    truth = {s.name: s for s in truth}
    tracks = [s.to_weak_perspective() if s.projection == "perspective" else s for s in seqs]
    if args.unit_frames:
        tracks = [unit_frames(s) for s in tracks]
    every_cut = multiview_cuts(tracks)
    cuts = every_cut[::args.every]
    gt = [np.stack([truth[seqs[i].name].points_3d[t] for i, t in c.sources]) for c in cuts]  # (F, P, 3) mm
    rows, records = [], []
    for text in args.methods.split(","):
        method, params = parse_method(text.strip())
        t0 = time.perf_counter()
        dataset = f"h36m-{stride}-{args.input}" + ("-unit-frames" if args.unit_frames else "")
        shapes, failed, reused = solve_cuts(cuts, method, params, out_dir=Path(args.out) / "cuts", dataset=dataset,
                                            jobs=args.jobs, progress=not args.no_progress)
        wall = time.perf_counter() - t0
        folder = _cache_folder(Path(args.out) / "cuts", dataset, method, params)
        seconds = [float(read_npz(_cut_path(folder, c), "a saved label")["seconds"]) for c in cuts]
        flips = resolve_reflections(shapes)
        errors = []
        for rec, flip, g in zip(shapes, flips, gt):
            if not np.isfinite(rec).any():  # a failed cut (a point no frame shows is NaN in a solved one)
                continue
            rec = rec * _MIRROR if flip else rec
            errors.append(label_errors_per_frame(rec, g))
        err = float(np.concatenate(errors).mean()) if errors else None
        per_cut = float(np.mean(seconds))
        label = method + (":" + ";".join(f"{k}={v}" for k, v in params.items()) if params else "")
        rows.append([label, len(cuts), len(failed), err, per_cut, per_cut * len(every_cut) / 2 / 60])
        records.append({"solver": label, "cuts": len(cuts), "failed": len(failed), "label_mpjpe_mm": err,
                        "seconds_per_cut": per_cut, "wall_seconds": wall, "reused_cuts": reused,
                        "all_cuts": len(every_cut), "minutes_all_cuts_2_cores": per_cut * len(every_cut) / 2 / 60})
    text = (f"### Pseudo-labels on every {args.every}th training cut of {', '.join(subjects)} ({args.input}"
            + (", each frame scaled to a unit xy norm" if args.unit_frames else "") + "): "
            "label MPJPE (mm, PRN protocol as the network learns them) and cost\n\n"
            + markdown_table(["solver", "cuts", "failed", "label MPJPE (mm)", "s per cut (1 thread)",
                              f"minutes for all {len(every_cut)} cuts of these subjects on 2 cores"], rows))
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "label_quality.md").write_text(text + "\n")
    write_json(out / "label_quality.json", {"meta": run_metadata(study="label_quality", subjects=subjects,
                                                                 every=args.every, input=args.input,
                                                                 unit_frames=args.unit_frames),
                                            "rows": records})
    print(f"\nwrote {out}/label_quality.md, label_quality.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
