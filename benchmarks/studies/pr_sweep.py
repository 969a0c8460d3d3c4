"""PR's regulariser and start on the CMU files: the study behind PR's defaults (``nrsfm/solvers/pr.py``).

    OMP_NUM_THREADS=1 python -m benchmarks.studies.pr_sweep [--root DIR] [--jobs N] [--sequences a,b] [--out DIR]
                                                    [--rerun] [--no-progress]

Runs the ``pr`` solver on every file under ``DIR/nrsfm`` with the paper's
formulation (nuclear norm of the aligned shapes, rigid start) and with the
log-determinant of the centred aligned shapes at three offsets, each from
CSF2 with its automatic K and with the reference K of ``benchmarks.classic``.
A default is robust when both CSF2 starts end at the same e3D. Prints one
Markdown table (camera-frame e3D and, per configuration, the summed time) and
writes CSV/JSON and a plot (``pr_sweep.png``) to ``runs/pr_sweep``. Without
data (no ``--root``, ``$NRSFM_DATA`` unset) it runs on the synthetic stand-ins
of ``benchmarks.classic``. Solves are saved and resumed as in ``benchmarks.classic``
(``OUT/cells``; ``--rerun`` solves everything again).
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

from benchmarks.common import (code_hash, config_hash, markdown_table, run_cells_from_args, run_metadata, write_csv,
                               write_json, write_text_atomic)

log = logging.getLogger("benchmarks.studies.pr_sweep")

#: (label, PR parameters); ``init_K="reference"`` takes CSF2's reference K of the sequence.
CONFIGS = [
    ("paper: nuclear, uncentred, rigid start", {"regulariser": "nuclear", "centre": False, "init": "rigid"}),
    *[(f"logdet d={d:g}, CSF2 {k} K", {"delta_rel": d, "init_K": k}) for d in (3e-3, 1e-3, 3e-4)
      for k in ("automatic", "reference")],
]


def run_one(path: str, label: str, config: dict) -> dict:
    """One PR solve; errors are recorded, never raised."""
    import nrsfm
    from benchmarks.classic import REFERENCE_SETTINGS, load_benchmark_sequence
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d

    seq = load_benchmark_sequence(path)
    kw = dict(config)
    if kw.get("init_K") == "automatic":
        kw["init_K"] = 0
    elif kw.get("init_K") == "reference":
        kw["init_K"] = REFERENCE_SETTINGS["csf2"].get(seq.name, {}).get("K", 0)
    row = {"sequence": seq.name, "config": label, "params": kw}
    try:
        rec = nrsfm.solve(seq, "pr", **kw)
    except NRSfMError as exc:
        return {**row, "status": "error", "why": str(exc)}
    return {**row, "status": "ok", "e3d_camera": e3d(rec.points_3d, seq.points_3d), "seconds": rec.runtime_s,
            "iterations": rec.iterations, "converged": rec.converged, "init": rec.info["init"]}


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import data_where, job_identity, parse_data_benchmark, plot_results

    parsed = parse_data_benchmark("pr_sweep", __doc__, argv, jobs_help="parallel solves (joblib)")
    if parsed is None:
        return 2
    args, folder, files, _ = parsed
    t0 = time.perf_counter()
    log.info("pr_sweep: %d sequences x %d configurations, %d jobs", len(files), len(CONFIGS), args.jobs)
    out = Path(args.out)
    code = code_hash(__file__, Path(__file__).parent.parent / "classic.py")
    identity = {f: job_identity(f) for f in files}
    cells = [(f"{Path(f).stem}-{config_hash({'label': label})}", {**identity[f], "config": cfg, "code": code},
              (f, label, cfg)) for f in files for label, cfg in CONFIGS]
    done = run_cells_from_args(args, cells, run_one, out, "pr_sweep")
    if done is None:
        return 130
    rows, reused = done
    names = [Path(f).stem for f in files]
    cell = {(r["sequence"], r["config"]): r for r in rows}
    table = []
    for label, _ in CONFIGS:
        rs = [cell[(n, label)] for n in names]
        table.append([label, *(f"{r['e3d_camera']:.4f}" if r["status"] == "ok" else f"not run: {r['why']}"
                               for r in rs), f"{sum(r.get('seconds', 0.0) for r in rs):.1f}"])
    md = markdown_table(["configuration (camera-frame e3D)", *names, "time (s), all files"], table)
    where = data_where(folder, files)
    print(f"### PR regulariser and start ({where}, one thread per solve)\n\n{md}\n")
    write_csv(out / "pr_sweep.csv", [{k: v for k, v in r.items() if k != "params"} | {"params": str(r["params"])}
                                     for r in rows])
    write_json(out / "pr_sweep.json", {"meta": run_metadata(jobs=args.jobs, data=str(folder or "stand-ins"),
                                                           cells_reused=reused),
                                       "rows": rows})
    write_text_atomic(out / "pr_sweep.md", md + "\n")
    plot_results([{**r, "method": r["config"]} for r in rows], out / "pr_sweep.png")
    print(f"wrote {out}/pr_sweep.md, pr_sweep.csv, pr_sweep.json, pr_sweep.png ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
