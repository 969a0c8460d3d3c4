"""EM-PND from other solvers' reconstructions, and the mean of those runs: a study of EM-PND's start.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.empnd_starts [--root DIR] [--jobs N] [--sequences a,b]
                                                        [--starts auto,spm,pr] [--out DIR] [--rerun] [--no-progress]

Runs the ``empnd`` solver on every file under ``DIR/nrsfm`` once per start
(its ``init`` parameter: ``auto`` is the default, the authors' factorisation
start on complete tracks; ``spm`` and ``pr`` start from those solvers'
reconstructions) and scores each run and the mean of the runs' camera-frame
shapes, each run first fitted to the first by one global orthogonal matrix
(no ground truth involved). The mean asks whether the runs' errors are
independent enough to cancel. Prints one Markdown table (camera-frame e3D,
EM-PND's final cost per shape dimension, the best published e3D of NOTES.md)
and writes CSV/JSON to ``runs/empnd_starts``. Without data (no ``--root``,
``$NRSFM_DATA`` unset) it runs on the synthetic stand-ins of
``benchmarks.classic``. One cell per sequence, saved and resumed as in
``benchmarks.classic`` (``--rerun`` solves everything again).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import (code_hash, config_hash, markdown_table, run_cells_from_args, run_metadata, write_csv,
                               write_json, write_text_atomic)

log = logging.getLogger("benchmarks.studies.empnd_starts")


def fit_to(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """`(F, P, 3)` shapes ``x`` centred per frame and turned by the one orthogonal 3 x 3 matrix (reflection
    allowed, as in :func:`nrsfm.metrics.e3d`) that best maps them onto the centred ``ref`` in least squares."""
    x = x - x.mean(axis=1, keepdims=True)
    ref = ref - ref.mean(axis=1, keepdims=True)
    q = np.linalg.lstsq(x.reshape(-1, 3), ref.reshape(-1, 3), rcond=None)[0]
    u, _, vt = np.linalg.svd(q)
    return x @ (u @ vt)


def run_one(job: str, starts: tuple[str, ...]) -> list[dict]:
    """EM-PND from each start on one sequence, then the mean of the runs; errors are recorded, never raised."""
    import nrsfm
    from benchmarks.classic import load_benchmark_sequence
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d

    seq = load_benchmark_sequence(job)
    rows, shapes = [], []
    for init in starts:
        t0 = time.perf_counter()
        row = {"sequence": seq.name, "start": init}
        try:
            rec = nrsfm.solve(seq, "empnd", init=init)
        except NRSfMError as exc:
            rows.append({**row, "status": "not run", "why": str(exc), "seconds": time.perf_counter() - t0})
            continue
        # seconds include the other solver's run for the spm / pr starts
        rows.append({**row, "status": "ok", "e3d_camera": e3d(rec.points_3d, seq.points_3d),
                     "cost": rec.info["cost"], "iterations": rec.iterations, "seconds": time.perf_counter() - t0})
        shapes.append((init, rec.points_3d))
    if len(shapes) > 1:
        ref = shapes[0][1]
        mean = np.mean([fit_to(x, ref) for _, x in shapes], axis=0)
        rows.append({"sequence": seq.name, "start": "mean(" + ",".join(n for n, _ in shapes) + ")", "status": "ok",
                     "e3d_camera": e3d(mean, seq.points_3d), "seconds": 0.0})
    return rows


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import REFERENCE, data_where, job_identity, parse_data_benchmark
    from nrsfm.solvers.empnd import INITS

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--starts", default="auto,spm,pr",
                       help=f"comma-separated EM-PND starts among {', '.join(INITS)} (default: auto,spm,pr)")

    def check(args: argparse.Namespace) -> tuple[str, ...]:
        starts = tuple(s.strip() for s in args.starts.split(",") if s.strip())
        if not starts or any(s not in INITS for s in starts):
            raise ValueError(f"--starts: expected names among {', '.join(INITS)}, got {args.starts!r}")
        return starts

    parsed = parse_data_benchmark("empnd_starts", __doc__, argv, jobs_help="parallel sequences (joblib)",
                                  options=options, check=check)
    if parsed is None:
        return 2
    args, folder, files, starts = parsed
    t0 = time.perf_counter()
    log.info("empnd_starts: %d sequences x %d starts, %d jobs", len(files), len(starts), args.jobs)
    out = Path(args.out)
    code = code_hash(__file__, Path(__file__).parent.parent / "classic.py")
    cells = [(f"{Path(f).stem}-{config_hash({'starts': starts})}", {**job_identity(f), "starts": starts,
                                                                     "code": code}, (f, starts)) for f in files]
    done = run_cells_from_args(args, cells, run_one, out, "empnd_starts")
    if done is None:
        return 130
    results, reused = done
    rows = [r for cell_rows in results for r in cell_rows]
    by_seq: dict[str, list[dict]] = {}
    for r in rows:
        by_seq.setdefault(r["sequence"], []).append(r)
    labels = list(dict.fromkeys(r["start"] for r in rows))
    table = []
    for name, rs in by_seq.items():
        cell = {r["start"]: r for r in rs}
        published = [v[0] for v in REFERENCE.get(name, {}).values()]

        def fmt(label: str) -> str:
            r = cell.get(label)
            if r is None:
                return "–"
            if r["status"] != "ok":
                return f"not run: {r['why']}"
            return f"{r['e3d_camera']:.5f}" + (f" ({r['cost']:.4f})" if "cost" in r else "")

        table.append([name, *(fmt(label) for label in labels), f"{min(published):.4f}" if published else "–"])
    md = markdown_table(["sequence", *(f"{label}: e3D (cost)" if not label.startswith("mean") else f"{label}: e3D"
                                       for label in labels), "best published"], table)
    where = data_where(folder, files)
    print(f"### EM-PND's start ({where}; camera-frame e3D, final PND cost per dimension)\n\n{md}\n")
    write_csv(out / "empnd_starts.csv", rows)
    write_json(out / "empnd_starts.json", {"meta": run_metadata(jobs=args.jobs, data=str(folder or "stand-ins"),
                                                               starts=list(starts), cells_reused=reused),
                                           "rows": rows})
    write_text_atomic(out / "empnd_starts.md", md + "\n")
    print(f"wrote {out}/empnd_starts.md, empnd_starts.csv, empnd_starts.json ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
