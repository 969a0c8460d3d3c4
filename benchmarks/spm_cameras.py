"""SPM's cameras refined by its own shape objective (``--set refine_cameras=true``): a study of the yoga gap.

    OMP_NUM_THREADS=1 python -m benchmarks.spm_cameras [--root DIR] [--jobs N] [--sequences a,b]
        [--lams 0,0.3,3,30,300] [--iters 300] [--out DIR] [--rerun] [--no-progress]

SPM's cameras minimise an orthonormality residual of ``pi_f G`` (:func:`nrsfm.solvers.spm.camera_step`); on
yoga that minimum is 20% above the authors' object-frame e3D. This study asks whether the shape step's own
objective, the nuclear norm of ``S#``, picks better cameras: for every weight ``lam`` of ``--lams`` it runs
:func:`nrsfm.solvers.spm.refine_cameras_nuclear` (``||S#||_* / ||S#_0||_* + lam * orthonormality residual``,
jointly over ``G`` and the depths, ``--iters`` L-BFGS iterations) from SPM's cameras, then SPM's shape step
(:func:`nrsfm.solvers.spm.shape_admm`) on the refined cameras. Each cell: object-frame e3D (the frame of the
authors' numbers), the camera error against the ground-truth cameras, and the camera-frame e3D; "SPM" is the
solver's default result (no refinement), "authors" the numbers of their example script. Files without a
moving ground-truth camera (dance, the shark) get the camera-frame e3D only. Without data it runs on the synthetic
stand-ins of ``benchmarks.classic``. Writes CSV/JSON/Markdown to ``runs/spm_cameras``; cells are saved and
resumed as in ``benchmarks.classic``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import (add_run_arguments, code_hash, config_hash, markdown_table, run_cells_from_args,
                               run_metadata, write_csv, write_json, write_text_atomic)

log = logging.getLogger("benchmarks.spm_cameras")


def parse_lams(text: str) -> list[float]:
    """``"0,0.3,3"``: non-negative weights of the orthonormality residual."""
    try:
        lams = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        lams = []
    if not lams or any(not (np.isfinite(v) and v >= 0) for v in lams):
        raise ValueError(f"--lams: expected comma-separated numbers >= 0, got {text!r}")
    return lams


def run_one(job: str, lams: list[float], iters: int) -> dict:
    """SPM's cameras, each weight's refinement and the scores of one sequence; errors are recorded, not raised."""
    import torch

    from benchmarks.classic import load_benchmark_sequence
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import camera_moves, e3d, rotation_error
    from nrsfm.solvers.spm import SPMParams, camera_step, choose_k, refine_cameras_nuclear, shape_admm

    torch.manual_seed(0)
    seq = load_benchmark_sequence(job)
    row = {"sequence": seq.name, "frames": seq.n_frames, "points": seq.n_points}
    if not seq.is_complete:
        return {**row, "status": "not run", "why": "SPM needs complete tracks"}
    params = SPMParams()
    wf = (seq.points_2d - seq.points_2d.mean(axis=1, keepdims=True)).transpose(0, 2, 1)  # (F, 2, P)
    wm = wf.reshape(-1, seq.n_points)
    t0 = time.perf_counter()
    try:
        k = choose_k(seq.name, wm, params.K)
        cameras = camera_step(wm, k, params.trace_weight)
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc)}

    def score(rot: np.ndarray) -> tuple[dict, np.ndarray]:
        depth, _ = shape_admm(wf, rot, tol=params.admm_tol, max_iter=params.admm_max_iter)
        points = np.concatenate([wf, depth[:, None]], axis=1).transpose(0, 2, 1)  # (F, P, 3)
        out = {"e3d_camera": e3d(points, seq.points_3d), "e3d_object": None, "camera_error": None}
        if seq.camera_rotations is not None and camera_moves(seq.camera_rotations):  # as benchmarks.classic
            out["e3d_object"] = e3d(points, seq.points_3d, frame="object", pred_rotations=rot,
                                    gt_rotations=seq.camera_rotations)
            out["camera_error"] = rotation_error(rot, seq.camera_rotations)
        return out, depth

    spm, depth = score(cameras.rotations)
    refined = []
    for lam in lams:
        t = time.perf_counter()
        rot = refine_cameras_nuclear(wf, cameras, depth, lam, iters)
        refined.append({"lam": lam, **score(rot)[0], "seconds": time.perf_counter() - t})
    return {**row, "status": "ok", "K": k, "spm": spm, "refined": refined, "seconds": time.perf_counter() - t0}


def _cell(s: dict) -> str:
    obj = f"{s['e3d_object']:.4f}" if s["e3d_object"] is not None else "–"
    cam = f"{s['camera_error']:.4f}" if s["camera_error"] is not None else "–"
    return f"{obj} / {cam} / {s['e3d_camera']:.4f}"


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import (SPM_REFERENCE, SPM_ROTATION_REFERENCE, add_data_arguments, benchmark_sequences,
                                    job_identity)
    from nrsfm.errors import NRSfMError

    p = argparse.ArgumentParser(prog="python -m benchmarks.spm_cameras", description=__doc__.split("\n\n")[0])
    add_data_arguments(p, "parallel sequences (joblib)")
    p.add_argument("--lams", default="0,0.3,3,30,300", help="weights of the orthonormality residual")
    p.add_argument("--iters", type=int, default=300, help="L-BFGS iterations of each refinement (default 300)")
    p.add_argument("--out", default="runs/spm_cameras", help="output folder (default: runs/spm_cameras)")
    add_run_arguments(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    try:
        lams = parse_lams(args.lams)
        if args.iters < 1:
            raise ValueError(f"--iters: expected a positive number of iterations, got {args.iters}")
        folder, files = benchmark_sequences(args.root, args.sequences, "spm_cameras")
    except (NRSfMError, ValueError) as exc:
        print(f"spm_cameras: error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    out = Path(args.out)
    key = {"lams": lams, "iters": args.iters}
    code = code_hash(__file__, Path(__file__).with_name("classic.py"))
    cells = [(f"{Path(f).stem}-{config_hash(key)}", {**job_identity(f), **key, "code": code},
              (f, lams, args.iters)) for f in files]
    done = run_cells_from_args(args, cells, run_one, out, "spm_cameras")
    if done is None:
        return 130
    results, reused = done
    table, rows = [], []
    for r in results:
        if r["status"] != "ok":
            log.warning("%s: not run: %s", r["sequence"], r["why"])
            table.append([r["sequence"], f"not run: {r['why']}", *([""] * (len(lams) + 1))])
            continue
        name = r["sequence"]
        authors = (f"{SPM_REFERENCE[name][0]} ({SPM_REFERENCE[name][1]}) / {SPM_ROTATION_REFERENCE.get(name, '–')}"
                   if name in SPM_REFERENCE else "–")
        table.append([name, _cell(r["spm"]), *(_cell(c) for c in r["refined"]), authors])
        rows.append({"sequence": name, "K": r["K"], "lam": None, **r["spm"]})
        rows.extend({"sequence": name, "K": r["K"], **c} for c in r["refined"])
    md = markdown_table(["sequence", "SPM", *(f"lam = {v:g}" for v in lams), "authors"], table)
    where = f"{len(files)} CMU files" if folder is not None else "synthetic stand-ins, no CMU data"
    text = (f"### SPM's cameras refined by the nuclear norm of S# ({where}, {args.iters} L-BFGS iterations)\n\n"
            f"Each cell: object-frame e3D / camera error / camera-frame e3D.\n\n{md}\n")
    print(text)
    write_csv(out / "spm_cameras.csv", rows)
    write_json(out / "spm_cameras.json", {"meta": run_metadata(
        benchmark="spm cameras", lams=lams, iters=args.iters, jobs=args.jobs, data=str(folder or "stand-ins"),
        cells_reused=reused, wall_s=time.perf_counter() - t0), "rows": rows})
    write_text_atomic(out / "spm_cameras.md", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
