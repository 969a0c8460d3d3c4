"""SPM's cameras refined by its own shape objective (``--set refine_cameras=true``): a study of the yoga gap.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.spm_cameras [--root DIR] [--jobs N] [--sequences a,b]
        [--lams 0,0.3,3,30,300] [--iters 300] [--starts N] [--out DIR] [--rerun] [--no-progress]

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

``--starts N`` also maps the minima of the camera step's own cost: its refinement of the corrective triple
(:func:`nrsfm.solvers.csf2.refine_triple`) from N random starts (normal entries at the scale of SPM's triple,
seeded by the sequence name), the distinct minima it ends at (:func:`same_cost`), how many
starts reach each, and each one's cameras scored as above, with the nuclear norm of ``S#`` at the shape step's
minimum relative to SPM's. It asks whether the authors' cameras could be another minimum of their cost.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from benchmarks.common import (code_hash, config_hash, markdown_table, run_cells_from_args, run_metadata, write_csv,
                               write_outputs)

log = logging.getLogger("benchmarks.studies.spm_cameras")


def parse_lams(text: str) -> list[float]:
    """``"0,0.3,3"``: non-negative weights of the orthonormality residual."""
    try:
        lams = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        lams = []
    if not lams or any(not (np.isfinite(v) and v >= 0) for v in lams):
        raise ValueError(f"--lams: expected comma-separated numbers >= 0, got {text!r}")
    return lams


def same_cost(a: float, b: float) -> bool:
    """Whether two costs of the camera step are one minimum: within 1e-6 (relative), or both below 1e-12 (the
    exact data's zero: 1e-29 to 1e-17 on the shark)."""
    return abs(a - b) <= 1e-6 * max(a, b) + 1e-12


def run_one(job: str, lams: list[float], iters: int, starts: int = 0) -> dict:
    """SPM's cameras, each weight's refinement, ``starts`` random starts of the camera step's refinement and the
    scores of one sequence; errors are recorded, not raised."""
    import zlib

    import torch

    from benchmarks.classic import REFERENCE_SETTINGS, load_benchmark_sequence
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import camera_moves, e3d, rotation_error
    from nrsfm.solvers.cameras import refine_triple
    from nrsfm.solvers.spm import (SPMParams, camera_step, choose_k, refine_cameras_nuclear, rotations_from_triple,
                                   shape_admm)

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
        k = choose_k(wm, params.K or REFERENCE_SETTINGS["spm"].get(seq.name, {}).get("K", 0))
        cameras = camera_step(wm, k, params.trace_weight)
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc)}

    def score(rot: np.ndarray) -> tuple[dict, np.ndarray]:
        depth, _ = shape_admm(wf, rot, tol=params.admm_tol, max_iter=params.admm_max_iter)
        points = np.concatenate([wf, depth[:, None]], axis=1).transpose(0, 2, 1)  # (F, P, 3)
        sharp = np.einsum("fji,fjp->fip", rot, points.transpose(0, 2, 1)).reshape(seq.n_frames, -1)  # S# rows
        out = {"e3d_camera": e3d(points, seq.points_3d), "e3d_object": None, "camera_error": None,
               "nuclear": float(np.linalg.svd(sharp, compute_uv=False).sum())}
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
    minima: list[dict] = []
    rng = np.random.default_rng(zlib.crc32(f"spm-starts-{seq.name}".encode()))
    for _ in range(starts):
        g0 = rng.standard_normal(cameras.g.shape) * np.linalg.norm(cameras.g) / np.sqrt(cameras.g.size)
        g, cost = refine_triple(cameras.pi, g0)
        same = [m for m in minima if same_cost(cost, m["cost"])]
        if same:
            same[0]["starts"] += 1
            continue
        rot, _ = rotations_from_triple(cameras.pi, g, cameras.reference)
        minima.append({"cost": cost, "starts": 1, **score(rot)[0]})
    minima.sort(key=lambda m: m["cost"])
    return {**row, "status": "ok", "K": k, "spm": {**spm, "cost": cameras.residual}, "refined": refined,
            "minima": minima, "starts": starts, "seconds": time.perf_counter() - t0}


def _cell(s: dict) -> str:
    obj = f"{s['e3d_object']:.4f}" if s["e3d_object"] is not None else "–"
    cam = f"{s['camera_error']:.4f}" if s["camera_error"] is not None else "–"
    return f"{obj} / {cam} / {s['e3d_camera']:.4f}"


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import (SPM_REFERENCE, SPM_ROTATION_REFERENCE, data_where, job_identity,
                                    parse_data_benchmark)

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--lams", default="0,0.3,3,30,300", help="weights of the orthonormality residual")
        p.add_argument("--iters", type=int, default=300, help="L-BFGS iterations of each refinement (default 300)")
        p.add_argument("--starts", type=int, default=0,
                       help="random starts of the camera step's refinement whose minima are scored (default 0: none)")

    def check(args: argparse.Namespace) -> list[float]:
        if args.iters < 1:
            raise ValueError(f"--iters: expected a positive number of iterations, got {args.iters}")
        if args.starts < 0:
            raise ValueError(f"--starts: expected a number of random starts >= 0, got {args.starts}")
        return parse_lams(args.lams)

    parsed = parse_data_benchmark("spm_cameras", __doc__, argv, jobs_help="parallel sequences (joblib)",
                                  options=options, check=check)
    if parsed is None:
        return 2
    args, folder, files, lams = parsed
    t0 = time.perf_counter()
    out = Path(args.out)
    key = {"lams": lams, "iters": args.iters, "starts": args.starts}
    code = code_hash(__file__, Path(__file__).parent.parent / "classic.py")
    cells = [(f"{Path(f).stem}-{config_hash(key)}", {**job_identity(f), **key, "code": code},
              (f, lams, args.iters, args.starts)) for f in files]
    done = run_cells_from_args(args, cells, run_one, out, "spm_cameras")
    if done is None:
        return 130
    results, reused = done
    table, rows, minima_table, minima_rows = [], [], [], []
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
        for m in r.get("minima", []):
            lowest = same_cost(m["cost"], r["spm"]["cost"])
            minima_rows.append({"sequence": name, "K": r["K"], "spm_minimum": lowest, **m})
            minima_table.append([name, f"{m['cost']:.4e}", f"{m['starts']} of {r['starts']}",
                                 "yes" if lowest else "", _cell(m), f"{m['nuclear'] / r['spm']['nuclear']:.4f}"])
    md = markdown_table(["sequence", "SPM", *(f"lam = {v:g}" for v in lams), "authors"], table)
    where = data_where(folder, files)
    text = (f"### SPM's cameras refined by the nuclear norm of S# ({where}, {args.iters} L-BFGS iterations)\n\n"
            f"Each cell: object-frame e3D / camera error / camera-frame e3D.\n\n{md}\n")
    if args.starts:
        text += (f"\n### Minima of the camera step's cost from {args.starts} random starts\n\n"
                 f"Scores: object-frame e3D / camera error / camera-frame e3D; the nuclear norm of S# at the shape "
                 f"step's minimum over SPM's.\n\n"
                 + markdown_table(["sequence", "cost", "starts", "SPM's", "scores", "nuclear norm / SPM's"],
                                  minima_table) + "\n")
    write_outputs(out, "spm_cameras", text, rows, run_metadata(
        benchmark="spm cameras", lams=lams, iters=args.iters, jobs=args.jobs, data=str(folder or "stand-ins"),
        cells_reused=reused, wall_s=time.perf_counter() - t0, starts=args.starts), minima=minima_rows)
    if args.starts:
        write_csv(out / "spm_cameras_minima.csv", minima_rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
