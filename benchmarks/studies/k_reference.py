"""CSF2's automatic K with other references: EM-PND (the default), PR, SPM, and weighted means of them.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.k_reference [--root DIR] [--jobs N] [--missing 0,0.2]
        [--k-max 12] [--out DIR] [--rerun] [--no-progress]

The agreement rule (:mod:`nrsfm.solvers.kselect`) keeps the largest K whose CSF2 reconstruction lies within a
tolerance of the least e3D to a reference that needs no K. This study asks whether another reference or
tolerance picks a better K. Per sequence of the tuning set (the CMU files) and of the validation set of
:mod:`benchmarks.defaults` (each ``--missing`` ratio on the validation set; the CMU files complete), one cell
solves CSF2 at every fixed K of that benchmark, EM-PND, PR and SPM at their defaults, and measures each K's
distance to the references of :data:`REFERENCES`: each solver alone and weighted means of them
(:func:`nrsfm.solvers.consensus.average_reconstructions`; the consensus solver's mean of EM-PND and PR at its
weight 0.85). For every
(reference, tolerance 0, 5 or 10%) rule the table counts the sequences where the chosen K is within 10% of the
best fixed K (an oracle, chosen with the ground truth) and gives the worst ratio. A rule qualifies only by the
tuning set's column; the validation columns then say how it holds. Cells are saved and resumed as in
``benchmarks.classic``; outputs in ``runs/k_reference``. Without data the sets are the stand-ins of
``benchmarks.classic`` and ``benchmarks.defaults``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from benchmarks.common import code_hash, markdown_table, run_cells_from_args, run_metadata, write_outputs

log = logging.getLogger("benchmarks.studies.k_reference")

#: The references: name -> the solvers' weights in the mean (one solver: that solver's reconstruction).
REFERENCES = {"empnd": {"empnd": 1.0}, "pr": {"pr": 1.0}, "spm": {"spm": 1.0},
              "consensus 0.85": {"empnd": 0.85, "pr": 0.15}, "consensus 0.5": {"empnd": 0.5, "pr": 0.5},
              "empnd + spm": {"empnd": 0.5, "spm": 0.5}}
TOLERANCES = (0.0, 0.05, 0.1)


def run_one(job: str, tuning: bool, missing: float, k_max: int) -> dict:
    """CSF2 at every fixed K, EM-PND, PR and SPM on one sequence (a CMU file or stand-in of the tuning set, or a
    validation job): each K's e3D to the ground truth and to every reference of :data:`REFERENCES`. Errors are
    recorded, never raised."""
    import nrsfm
    from benchmarks.classic import load_benchmark_sequence
    from benchmarks.defaults import k_cap, load_job
    from nrsfm.datasets.synthetic import drop_entries
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d
    from nrsfm.solvers.consensus import average_reconstructions

    seq = drop_entries(load_benchmark_sequence(job) if tuning else load_job(job), missing)
    row = {"sequence": seq.name, "missing": missing}
    try:
        solved = {m: nrsfm.solve(seq, m) for m in ("empnd", "pr", "spm")}
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc)}
    refs = {n: average_reconstructions([solved[m] for m in w], list(w.values()))[0] for n, w in REFERENCES.items()}
    truth, dist = {}, {n: {} for n in refs}
    for k in range(1, k_cap(seq.n_frames, seq.n_points, k_max) + 1):
        try:
            shapes = nrsfm.solve(seq, "csf2", K=k).points_3d
        except NRSfMError:
            continue
        truth[str(k)] = e3d(shapes, seq.points_3d)
        for n, ref in refs.items():
            dist[n][str(k)] = e3d(shapes, ref)
    if not truth:
        return {**row, "status": "not run", "why": "no fixed K could be solved"}
    return {**row, "status": "ok", "e3d": truth, "distance": dist,
            "reference_e3d": {n: e3d(r, seq.points_3d) for n, r in refs.items()}}


def score(results: list[dict], reference: str, tolerance: float) -> tuple[int, int, float]:
    """(sequences within 10% of the best fixed K, sequences, worst ratio) of one rule over ``results``."""
    from nrsfm.solvers.kselect import agreeing_k

    ratios = [r["e3d"][agreeing_k(r["distance"][reference], tolerance)] / min(r["e3d"].values()) for r in results]
    return sum(x <= 1.1 for x in ratios), len(ratios), max(ratios)


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import job_identity
    from benchmarks.defaults import job_label, study_over_both_sets

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--missing", default="0,0.2", help="fractions of entries missing on the validation set")
        p.add_argument("--k-max", type=int, default=12, help="largest fixed K (default 12)")

    parsed = study_over_both_sets("k_reference", __doc__, argv, options)
    if parsed is None:
        return 2
    args, missing, (_, cmu), (folder, val) = parsed
    t0 = time.perf_counter()
    code = code_hash(__file__, Path(__file__).parent.parent / "defaults.py")
    sets = [("tuning", j, 0.0) for j in cmu] + [("validation", j, m) for j in val for m in missing]
    cells = []
    for which, j, m in sets:
        label = job_label(j)
        ident = job_identity(j) if Path(j).is_file() else {"job": j}
        cells.append((f"{label}-m{m:g}", {**ident, "missing": m, "k_max": args.k_max, "code": code},
                      (j, which == "tuning", m, args.k_max)))
    done = run_cells_from_args(args, cells, run_one, Path(args.out), "k_reference")
    if done is None:
        return 130
    results, reused = done
    for r in results:
        if r["status"] != "ok":
            log.warning("%s: not run: %s", r["sequence"], r["why"])
    columns = [("tuning", 0.0)] + [("validation", m) for m in missing]
    groups = {c: [r for (which, _, m), r in zip(sets, results) if (which, m) == c and r["status"] == "ok"]
              for c in columns}
    table, summary = [], []
    for ref in REFERENCES:
        for tol in TOLERANCES:
            cells_text = []
            for c in columns:
                if not groups[c]:
                    cells_text.append("–")
                    continue
                within, n, worst = score(groups[c], ref, tol)
                cells_text.append(f"{within} / {n} (worst {worst:.2f})")
                summary.append({"reference": ref, "tolerance": tol, "set": c[0], "missing": c[1], "within": within,
                                "sequences": n, "worst_ratio": worst})
            table.append([ref, f"{100 * tol:g}%", *cells_text])
    header = ["reference", "tolerance", *(f"{w} ({100 * m:g}% missing)" for w, m in columns)]
    text = ("### CSF2's automatic K by agreement with other references\n\nSequences whose chosen K is within 10% of "
            "CSF2's best fixed K (an oracle) and the worst ratio; the tuning set is the CMU files, complete.\n\n"
            + markdown_table(header, table) + "\n")
    write_outputs(Path(args.out), "k_reference", text, [r for r in results if r["status"] == "ok"], run_metadata(
        benchmark="CSF2 automatic K: references", data=str(folder or "stand-ins"), missing=missing,
        k_max=args.k_max, jobs=args.jobs, cells_reused=reused, wall_s=time.perf_counter() - t0), summary=summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
