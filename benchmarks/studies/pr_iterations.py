"""PR's stopping rule: the best on the CMU files, scored on the validation set of ``benchmarks.defaults``.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.pr_iterations [--root DIR] [--jobs N] [--caps 100,200,...]
        [--tols 1e-5,...] [--missing 0,0.2] [--out DIR] [--rerun] [--no-progress]

PR's log-determinant can keep falling after its shapes are nearest the ground truth: the late L-BFGS steps
shrink the small singular values of the aligned shapes below the true shapes' own, and the camera-frame e3D
rises again (the CMU dance, some Human3.6M motions). This study asks whether another stopping rule is a better
default: an iteration cap (``max_iter``, each of ``--caps``) or a looser relative function tolerance (``tol``,
each of ``--tols``, at the default cap: L-BFGS stops once an iteration lowers the objective by less than
``tol * max(|f|, 1)``). It solves ``pr`` at its defaults but for that one setting on the CMU files (the tuning
set, ``DIR/nrsfm``) and on the validation set of ``benchmarks.defaults`` (Human3.6M motions seen by a turning
camera, two synthetic faces), with and without 20% of the entries missing (the same entries as
``benchmarks.defaults``). The CMU cells alone name the best rule (the least geometric mean of e3D over the files
and fractions); the validation cells say whether it holds on motion it was not chosen on, the Human3.6M motions
also apart from the faces. Per set and fraction the table gives the geometric mean of e3D and the number of
sequences within 10% of their best rule (an oracle: chosen with the ground truth). Cells are saved and resumed as
in ``benchmarks.classic``; outputs in ``runs/pr_iterations``. Without data the CMU files are the synthetic
stand-ins of ``benchmarks.classic`` and the motions those of ``benchmarks.defaults``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import code_hash, markdown_table, run_cells_from_args, run_metadata, write_outputs

log = logging.getLogger("benchmarks.studies.pr_iterations")

#: The caps compared (2000: PR's default).
CAPS = (100, 200, 300, 500, 2000)
#: The relative function tolerances compared at the default cap (PR's default: 1e-10).
TOLS = (1e-5, 3e-5, 1e-4)


def rule_label(setting: dict) -> str:
    """A stopping rule's name in tables: ``max_iter=200`` or ``tol=3e-05``."""
    (name, value), = setting.items()
    return f"{name}={value:g}"


def run_one(job: str, setting: dict, missing: float) -> dict:
    """PR at its defaults but for ``setting`` (``{"max_iter": N}`` or ``{"tol": T}``) on one job of
    ``benchmarks.defaults``; errors are recorded."""
    import nrsfm
    from nrsfm.datasets.synthetic import drop_entries
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d

    from benchmarks.defaults import load_job

    seq = drop_entries(load_job(job), missing)
    row = {"sequence": seq.name, "rule": rule_label(setting), "missing": missing}
    try:
        rec = nrsfm.solve(seq, "pr", **setting)
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc)}
    return {**row, "status": "ok", "e3d": e3d(rec.points_3d, seq.points_3d), "seconds": rec.runtime_s,
            "iterations": rec.iterations, "converged": rec.converged}


def _caps(text: str) -> tuple[int, ...]:
    try:
        caps = tuple(sorted({int(v) for v in text.split(",")}))
    except ValueError:
        caps = ()
    if not caps or caps[0] < 1:
        raise argparse.ArgumentTypeError(f"expected comma-separated iteration counts >= 1 such as 200,2000, got "
                                         f"{text!r}")
    return caps


def _tols(text: str) -> tuple[float, ...]:
    if not text.strip():
        return ()
    try:
        tols = tuple(sorted({float(v) for v in text.split(",")}))
    except ValueError:
        tols = (0.0,)
    if not 0 < tols[0] <= tols[-1] < 1:
        raise argparse.ArgumentTypeError(f"expected comma-separated tolerances in (0, 1) such as 1e-5,1e-4 (or "
                                         f"nothing), got {text!r}")
    return tols


def _gmean(values: list[float]) -> float:
    from scipy.stats import gmean

    return float(gmean(values)) if values else float("nan")


def summarise(rows: list[dict], rules: list[str]) -> tuple[list[list], str | None, dict[str, float]]:
    """Per (set, missing, rule): the geometric mean of e3D (the Human3.6M motions' apart), the sequences within
    10% of their best rule and the worst ratio to it; and the best rule on the CMU rows with the geometric mean of
    each rule there (None and {} where a CMU cell failed)."""
    ok = [r for r in rows if r["status"] == "ok"]
    best = {}
    for r in ok:
        key = (r["set"], r["sequence"], r["missing"])
        best[key] = min(best.get(key, np.inf), r["e3d"])
    table, tuning = [], {}
    for which in ("cmu", "validation"):
        for miss in sorted({r["missing"] for r in rows}):
            for rule in rules:
                cell = [r for r in rows if r["set"] == which and r["missing"] == miss and r["rule"] == rule]
                if not cell:
                    continue
                good = [r for r in cell if r["status"] == "ok"]
                ratios = [r["e3d"] / best[(which, r["sequence"], miss)] for r in good]
                h36m = [r["e3d"] for r in good if r["sequence"].startswith("h36m")]
                if which == "cmu":
                    tuning.setdefault(rule, []).extend(r["e3d"] if r["status"] == "ok" else np.inf for r in cell)
                table.append([which, f"{100 * miss:.0f}%", rule, f"{_gmean([r['e3d'] for r in good]):.4f}",
                              f"{_gmean(h36m):.4f}" if h36m else "-", f"{sum(q <= 1.1 for q in ratios)} of {len(cell)}",
                              f"{max(ratios, default=float('nan')):.2f}",
                              f"{sum(r.get('seconds', 0.0) for r in good):.0f}"])
    scores = {rule: _gmean(v) for rule, v in tuning.items()}
    if not scores or not np.isfinite(max(scores.values())):
        return table, None, {}
    return table, min(scores, key=scores.get), scores


def main(argv: list[str] | None = None) -> int:
    from nrsfm.solvers.pr import PRParams

    from benchmarks.classic import job_identity
    from benchmarks.defaults import job_label, study_over_both_sets

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--caps", type=_caps, default=CAPS, help="comma-separated L-BFGS iteration caps")
        p.add_argument("--tols", type=_tols, default=TOLS,
                       help="comma-separated relative function tolerances at the default cap ('' for none)")
        p.add_argument("--missing", default="0,0.2", help="comma-separated fractions of entries to mark missing")

    parsed = study_over_both_sets("pr_iterations", __doc__, argv, options)
    if parsed is None:
        return 2
    args, missing, (cmu_folder, cmu), (val_folder, val) = parsed
    t0 = time.perf_counter()
    code = code_hash(__file__, Path(__file__).parent.parent / "defaults.py")
    settings = [{"max_iter": c} for c in args.caps] + [{"tol": t} for t in args.tols]
    rules = [rule_label(st) for st in settings]
    sets = {**{j: "cmu" for j in cmu}, **{j: "validation" for j in val}}
    names = {j: job_label(j) for j in sets}
    # a file is known by its bytes (a changed file is solved again), a generated job by its name
    ident = {j: job_identity(j) if Path(j).is_file() else {"job": names[j]} for j in sets}
    cells = [(f"{names[j]}-{rule_label(st)}-m{miss:g}", {**ident[j], "set": s, **st, "missing": miss, "code": code},
              (j, st, miss)) for j, s in sets.items() for miss in missing for st in settings]
    done = run_cells_from_args(args, cells, run_one, Path(args.out), "pr_iterations")
    if done is None:
        return 130
    results, reused = done
    rows = [{**r, "set": sets[c[2][0]]} for r, c in zip(results, cells)]
    table, best, scores = summarise(rows, rules)
    default = rule_label({"max_iter": PRParams().max_iter})
    if best is None:
        verdict = "a CMU cell failed: no best rule"
    elif default in scores:
        verdict = (f"{best}, geometric mean {scores[best]:.4f} against {scores[default]:.4f} at PR's default "
                   f"({default}, tol={PRParams().tol:g}; {100 * (1 - scores[best] / scores[default]):.1f}% lower)")
    else:
        verdict = f"{best}, geometric mean {scores[best]:.4f} (PR's default, {default}, not among the rules)"
    per_seq = {}
    for r in rows:
        per_seq.setdefault((r["set"], r["sequence"], r["missing"]), {})[r["rule"]] = \
            f"{r['e3d']:.4f}" if r["status"] == "ok" else "failed"
    detail = [[s, n, f"{100 * m:.0f}%", *(v.get(c, "-") for c in rules)] for (s, n, m), v in per_seq.items()]
    where = ", ".join(f"{w}: {f}" for w, f in (("CMU", cmu_folder), ("validation", val_folder)) if f) or \
        "synthetic stand-ins"
    text = (f"### PR's stopping rule ({where}; one thread per solve)\n\n"
            + markdown_table(["set", "missing", "rule", "geometric mean e3D", "Human3.6M motions",
                              "within 10% of the best rule (oracle)", "worst ratio", "time (s)"], table)
            + f"\n\nBest rule on the CMU cells (least geometric mean of e3D, both fractions): {verdict}\n\n"
            + markdown_table(["set", "sequence", "missing", *rules], detail) + "\n")
    write_outputs(Path(args.out), "pr_iterations", text, rows, run_metadata(
        study="pr_iterations", caps=list(args.caps), tols=list(args.tols), missing=missing, jobs=args.jobs,
        cells_reused=reused, data=where, wall_s=time.perf_counter() - t0), cmu_best=best, cmu_geometric_mean=scores)
    return 0


if __name__ == "__main__":
    sys.exit(main())
