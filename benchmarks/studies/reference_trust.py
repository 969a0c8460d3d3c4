"""Can the automatic K tell, without ground truth, when its reference fails? EM-PND against PR as a check.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.reference_trust [--root DIR] [--jobs N] [--k-max 12]
        [--out DIR] [--rerun] [--no-progress]

The agreement rule (:mod:`nrsfm.solvers.kselect`) keeps the K whose reconstruction lies nearest EM-PND's. Where
EM-PND is far from the ground truth the rule follows it, so it would need a check of the reference that needs no
ground truth, and the obvious one is a second solver without K: where EM-PND and PR disagree, at least one of them
is wrong. This study measures whether that disagreement flags the sequences where the rule fails. Per 17-joint
motion of the validation and the test set of :mod:`benchmarks.defaults` (complete tracks; the faces, where every
solver is near exact, are left out), one cell solves EM-PND and PR at their defaults and CSF2 and SPM at every
fixed K up to the cap of ``benchmarks.defaults``, and records

* each reconstruction's camera-frame e3D;
* the disagreement ``d(EM-PND, PR)``: PR's e3D to EM-PND's reconstruction (:func:`nrsfm.metrics.e3d`, the
  distance the rule uses);
* each reconstruction's depth flips (:func:`nrsfm.solvers.kselect.depth_flips`: the fraction of frame pairs
  between which its depth reverses), EM-PND's among them;
* the rule's K for CSF2 (from K = 1) and SPM (from K = 2), computed from the same solves as
  :mod:`nrsfm.solvers.kselect` does on complete tracks (:func:`~nrsfm.solvers.kselect.agreement_choice`), and its
  ratio to the best fixed K (an oracle).

The table lists the sequences by disagreement, largest first; the summary gives Spearman's rank correlation of the
disagreement with EM-PND's e3D and, for each solver, the disagreement's rank among the sequences at every one
where the rule misses its best fixed K by more than 10%. A useful check would put those near the top. Cells are
saved and resumed as in ``benchmarks.classic``; outputs in ``runs/reference_trust``. Without data the motions are
the synthetic stand-ins of ``benchmarks.defaults``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from benchmarks.common import code_hash, markdown_table, parse_study_arguments, run_cells_from_args, run_metadata, \
    write_outputs

log = logging.getLogger("benchmarks.studies.reference_trust")

#: The solvers whose automatic K is scored, and the smallest K their rule tries (:mod:`nrsfm.solvers.kselect`).
RULE_FROM = {"csf2": 1, "spm": 2}
#: A rule misses where its K's e3D is above this many times the best fixed K's.
MISS = 1.1


def run_one(job: str, k_max: int) -> dict:
    """EM-PND, PR, and CSF2 and SPM at every fixed K on one motion: e3D, the disagreement of EM-PND and PR, each
    K's distance to EM-PND, every reconstruction's depth flips. Errors are recorded, never raised."""
    import nrsfm
    from benchmarks.defaults import k_cap, load_job
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d
    from nrsfm.solvers.kselect import depth_flips

    seq = load_job(job)
    row = {"sequence": seq.name}
    t0 = time.perf_counter()
    try:
        refs = {m: nrsfm.solve(seq, m).points_3d for m in ("empnd", "pr")}
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc)}
    truth: dict[str, dict[str, float]] = {m: {} for m in RULE_FROM}
    to_empnd: dict[str, dict[str, float]] = {m: {} for m in RULE_FROM}
    flips: dict[str, dict[str, float]] = {m: {} for m in RULE_FROM}
    for m in RULE_FROM:
        for k in range(1, k_cap(seq.n_frames, seq.n_points, k_max) + 1):
            try:
                shapes = nrsfm.solve(seq, m, K=k).points_3d
            except NRSfMError as exc:
                log.warning("%s: %s at K = %d: %s", seq.name, m, k, exc)
                continue
            truth[m][str(k)] = e3d(shapes, seq.points_3d)
            to_empnd[m][str(k)] = e3d(shapes, refs["empnd"])
            flips[m][str(k)] = depth_flips(shapes)
    return {**row, "status": "ok", "reference_e3d": {m: e3d(r, seq.points_3d) for m, r in refs.items()},
            "disagreement": e3d(refs["pr"], refs["empnd"]), "e3d": truth, "distance": to_empnd, "flips": flips,
            "reference_flips": {m: depth_flips(r) for m, r in refs.items()},
            "seconds": time.perf_counter() - t0}


def rule_ratio(row: dict, solver: str) -> tuple[str, float] | None:
    """(the agreement rule's K, its e3D over the best fixed K's) for ``solver`` on one cell, None where no K of
    the rule's range was solved. A row without depth flips passes over no K."""
    from nrsfm.solvers.kselect import agreement_choice

    dist = {k: d for k, d in row["distance"][solver].items() if int(k) >= RULE_FROM[solver]}
    if not dist:
        return None
    flips = row.get("flips", {}).get(solver, {})
    k = agreement_choice(dist, {k: flips.get(k, 0.0) for k in dist})
    return k, row["e3d"][solver][k] / min(row["e3d"][solver].values())


def ranks_of_misses(rows: list[dict], solver: str) -> list[int]:
    """The disagreement's rank (1: the largest) of every row where ``solver``'s rule misses (:data:`MISS`)."""
    order = sorted(range(len(rows)), key=lambda i: -rows[i]["disagreement"])
    rank = {i: n + 1 for n, i in enumerate(order)}
    return sorted(rank[i] for i, r in enumerate(rows) if (got := rule_ratio(r, solver)) and got[1] > MISS)


def main(argv: list[str] | None = None) -> int:
    from scipy.stats import spearmanr

    from benchmarks.defaults import job_label, validation_jobs
    from nrsfm.errors import NRSfMError

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--k-max", type=int, default=12, help="largest fixed K (default 12)")

    args = parse_study_arguments("reference_trust", __doc__, argv, options)
    t0 = time.perf_counter()
    try:
        if args.k_max < 1:
            raise ValueError(f"--k-max: expected a K >= 1, got {args.k_max}")
        sets = [(which, *validation_jobs(args.root, which)) for which in ("validation", "test")]
    except (NRSfMError, ValueError) as exc:
        print(f"reference_trust: error: {exc}", file=sys.stderr)
        return 2
    jobs = [(which, j) for which, _, js in sets for j in js if not j.startswith("face:")]
    code = code_hash(__file__, Path(__file__).parent.parent / "defaults.py")
    cells = [(job_label(j), {"job": j, "k_max": args.k_max, "code": code}, (j, args.k_max)) for _, j in jobs]
    done = run_cells_from_args(args, cells, run_one, Path(args.out), "reference_trust")
    if done is None:
        return 130
    results, reused = done
    rows = []
    for (which, _), r in zip(jobs, results):
        if r["status"] != "ok":
            log.warning("%s: not run: %s", r["sequence"], r["why"])
            continue
        rows.append({**r, "set": which})
    table = []
    for r in sorted(rows, key=lambda r: -r["disagreement"]):
        rules = [rule_ratio(r, m) for m in RULE_FROM]
        table.append([r["set"], r["sequence"], f"{r['disagreement']:.3f}", f"{r['reference_e3d']['empnd']:.3f}",
                      f"{r['reference_e3d']['pr']:.3f}", f"{r['reference_flips']['empnd']:.3f}",
                      *(f"{got[1]:.2f} ({got[0]})" if got else "–" for got in rules)])
    summary = {"sequences": len(rows)}
    if len(rows) > 1:
        rho = spearmanr([r["disagreement"] for r in rows], [r["reference_e3d"]["empnd"] for r in rows]).statistic
        summary["spearman_disagreement_empnd_e3d"] = float(rho)
    for m in RULE_FROM:
        summary[f"{m}_miss_ranks"] = ranks_of_misses(rows, m)
    lines = [f"{m}: the rule misses by more than {MISS:g} times on {len(summary[f'{m}_miss_ranks'])} of "
             f"{len(rows)}, at disagreement ranks {summary[f'{m}_miss_ranks'] or '–'}" for m in RULE_FROM]
    if "spearman_disagreement_empnd_e3d" in summary:
        lines.insert(0, f"Spearman's rank correlation of the disagreement with EM-PND's e3D: "
                        f"{summary['spearman_disagreement_empnd_e3d']:.2f}")
    text = ("### EM-PND against PR as a check of the automatic K's reference\n\nComplete tracks, camera-frame e3D; "
            "by disagreement d(EM-PND, PR), largest first; the rule's ratio to the best fixed K (its K).\n\n"
            + markdown_table(["set", "sequence", "d(EM-PND, PR)", "EM-PND", "PR", "EM-PND's depth flips", "csf2 rule",
                              "spm rule"], table)
            + "\n" + "".join(f"- {line}\n" for line in lines))
    write_outputs(Path(args.out), "reference_trust", text, rows, run_metadata(
        benchmark="the automatic K's reference: EM-PND against PR", data=str(sets[0][1] or "stand-ins"),
        k_max=args.k_max, jobs=args.jobs, cells_reused=reused, wall_s=time.perf_counter() - t0), summary=summary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
