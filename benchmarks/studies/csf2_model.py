"""CSF2 at every fixed K with other cameras and larger trajectory bases: is its K, its cameras or its model the limit?

    OMP_NUM_THREADS=1 python -m benchmarks.studies.csf2_model [--root DIR] [--jobs N] [--sequences a,b]
        [--k-max 12] [--out DIR] [--rerun] [--no-progress]

On the Human3.6M motions of the validation set of :mod:`benchmarks.defaults` every fixed K of CSF2 ends far from
the ground truth where SPM and EM-PND do not, so the automatic K chooses among poor solutions. This study asks
which part of CSF2 fails. Per sequence (complete tracks) it solves EM-PND and SPM at their defaults and then, for
every K from 1 to the cap of ``benchmarks.defaults``, five variants of CSF2:

* ``csf2``: the solver at that K (its own cameras, d = ceil(0.1 F));
* ``spm cameras`` / ``empnd cameras``: CSF2's shape step (:func:`nrsfm.solvers.csf2.fit_shape_gn`, the authors'
  start) with the camera rows of SPM's or EM-PND's reconstruction in place of its own;
* ``d = 0.2F`` / ``d = 0.4F``: the solver with two and four times its trajectory basis.

Each variant's cell: the least e3D over K, its K and the largest e3D over K (camera frame). If a variant with
better cameras or a larger basis reached SPM's e3D at some K, a better rule for K or better cameras would mend
CSF2; if every variant stays far above it, the shape model is the limit. The ground-truth cameras are no oracle
here: they see the world frame, in which the subject walks and turns, while an NRSfM camera follows the body.

A rule for K by stability is scored beside them: CSF2 at each K also solves the odd and the even frames alone,
and a K's *split distance* is the mean e3D of those two solves to its full solve on the same frames. The column
``steadiest K`` gives the K of the least split distance and its e3D over the least e3D of ``csf2``.

``--sequences`` keeps the sequences whose name contains one of the comma-separated words. Cells are saved and
resumed as in ``benchmarks.classic``; outputs in ``runs/csf2_model``. Without data the motions are the synthetic
stand-ins of ``benchmarks.defaults``.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import code_hash, markdown_table, parse_study_arguments, run_cells_from_args, run_metadata, \
    write_outputs

log = logging.getLogger("benchmarks.studies.csf2_model")

#: The variants of CSF2, in the table's order (module docstring).
VARIANTS = ("csf2", "spm cameras", "empnd cameras", "d = 0.2F", "d = 0.4F")


def shape_step_with_cameras(seq, rotations: np.ndarray, k: int) -> np.ndarray:
    """`(F, P, 3)` camera-frame shapes of CSF2's shape step at ``k`` on the complete ``seq`` with the cameras
    ``rotations`` `(F, 3, 3)` (their first two rows project) and d = max(ceil(0.1 F), k + 1) DCT vectors."""
    from nrsfm.lowrank import power_of_two_unit
    from nrsfm.solvers.csf2 import fit_shape_gn
    from nrsfm.solvers.dct import dct_basis

    w = seq.measurement_matrix()  # (2F, P)
    unit = power_of_two_unit(w, np.ones(w.shape, dtype=bool))
    wc = (w - w.mean(axis=1, keepdims=True)) / unit
    d = max(math.ceil(0.1 * seq.n_frames), k + 1)
    omega = dct_basis(seq.n_frames, d)  # (F, d)
    x, basis, *_ = fit_shape_gn(wc, rotations[:, :2, :], k, d, omega=omega)
    shapes = np.einsum("fk,kjp->fpj", omega @ x, basis)  # (F, P, 3) object frame
    points = np.einsum("fij,fpj->fpi", rotations, shapes)
    return (points - points.mean(axis=1, keepdims=True)) * unit


def run_one(job: str, k_max: int) -> dict:
    """EM-PND, SPM and the :data:`VARIANTS` of CSF2 at every fixed K on one validation job: e3D by variant and K.
    Errors are recorded, never raised."""
    import nrsfm
    from benchmarks.defaults import k_cap, load_job
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d

    seq = load_job(job)
    row = {"sequence": seq.name, "frames": seq.n_frames, "points": seq.n_points}
    t0 = time.perf_counter()
    try:
        refs = {m: nrsfm.solve(seq, m) for m in ("empnd", "spm")}
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc)}
    errors: dict[str, dict[str, float]] = {v: {} for v in VARIANTS}
    split: dict[str, float] = {}
    halves = [seq.select_frames(slice(i, None, 2)) for i in (0, 1)]
    for k in range(1, k_cap(seq.n_frames, seq.n_points, k_max) + 1):
        solves = {"csf2": {}, "d = 0.2F": {"d": max(math.ceil(0.2 * seq.n_frames), k + 1)},
                  "d = 0.4F": {"d": max(math.ceil(0.4 * seq.n_frames), k + 1)}}
        for name, extra in solves.items():
            try:
                points = nrsfm.solve(seq, "csf2", K=k, **extra).points_3d  # (F, P, 3)
                errors[name][str(k)] = e3d(points, seq.points_3d)
                if name == "csf2":
                    split[str(k)] = float(np.mean([e3d(nrsfm.solve(h, "csf2", K=k).points_3d, points[i::2])
                                                   for i, h in enumerate(halves)]))
            except NRSfMError as exc:
                log.warning("%s: %s at K = %d: %s", seq.name, name, k, exc)
        for m, rec in refs.items():
            errors[f"{m} cameras"][str(k)] = e3d(shape_step_with_cameras(seq, rec.rotations, k), seq.points_3d)
    return {**row, "status": "ok", "reference_e3d": {m: e3d(r.points_3d, seq.points_3d) for m, r in refs.items()},
            "e3d": errors, "split_distance": split, "seconds": time.perf_counter() - t0}


def variant_cell(by_k: dict[str, float]) -> str:
    """``least (K) – largest`` over the Ks of one variant, or "–" where none was solved."""
    if not by_k:
        return "–"
    best = min(by_k, key=by_k.get)
    return f"{by_k[best]:.4f} ({best}) – {max(by_k.values()):.4f}"


def steadiest_cell(split: dict[str, float], by_k: dict[str, float]) -> str:
    """``K (ratio)``: the K of the least split distance and its e3D over the least e3D of ``by_k``, or "–"."""
    solved = [k for k in split if k in by_k]
    if not solved:
        return "–"
    k = min(solved, key=split.get)
    return f"{k} ({by_k[k] / min(by_k.values()):.2f})"


def main(argv: list[str] | None = None) -> int:
    from benchmarks.defaults import job_label, validation_jobs
    from nrsfm.errors import NRSfMError

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--sequences", default="", help="keep the sequences whose name contains one of these words")
        p.add_argument("--k-max", type=int, default=12, help="largest fixed K (default 12)")

    args = parse_study_arguments("csf2_model", __doc__, argv, options)
    t0 = time.perf_counter()
    try:
        if args.k_max < 1:
            raise ValueError(f"--k-max: expected a K >= 1, got {args.k_max}")
        folder, jobs = validation_jobs(args.root)
    except (NRSfMError, ValueError) as exc:
        print(f"csf2_model: error: {exc}", file=sys.stderr)
        return 2
    names = {j: job_label(j) for j in jobs}  # without the data folder
    words = [w.strip() for w in args.sequences.split(",") if w.strip()]
    if words:
        kept = [j for j in jobs if any(w in names[j] for w in words)]
        if not kept:
            print(f"csf2_model: error: --sequences: no validation sequence contains any of {words}; the sequences: "
                  f"{', '.join(names.values())}", file=sys.stderr)
            return 2
        jobs = kept
    code = code_hash(__file__, Path(__file__).parent.parent / "defaults.py")
    cells = [(names[j], {"job": j, "k_max": args.k_max, "code": code}, (j, args.k_max)) for j in jobs]
    done = run_cells_from_args(args, cells, run_one, Path(args.out), "csf2_model")
    if done is None:
        return 130
    results, reused = done
    table = []
    for r in results:
        if r["status"] != "ok":
            log.warning("%s: not run: %s", r["sequence"], r["why"])
            table.append([r["sequence"], f"not run: {r['why']}", "", *([""] * len(VARIANTS)), ""])
            continue
        ref = r["reference_e3d"]
        table.append([r["sequence"], f"{ref['empnd']:.4f}", f"{ref['spm']:.4f}",
                      *(variant_cell(r["e3d"][v]) for v in VARIANTS),
                      steadiest_cell(r.get("split_distance", {}), r["e3d"]["csf2"])])
    text = ("### CSF2 with other cameras and larger trajectory bases\n\nCamera-frame e3D; each CSF2 cell: the least "
            "over K (that K) – the largest. Steadiest K: the K of the least split distance (its e3D over csf2's "
            "least).\n\n"
            + markdown_table(["sequence", "EM-PND", "SPM", *VARIANTS, "steadiest K"], table) + "\n")
    write_outputs(Path(args.out), "csf2_model", text, [r for r in results if r["status"] == "ok"], run_metadata(
        benchmark="CSF2: cameras and trajectory basis", data=str(folder or "stand-ins"), k_max=args.k_max,
        jobs=args.jobs, cells_reused=reused, wall_s=time.perf_counter() - t0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
