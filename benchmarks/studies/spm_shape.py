"""SPM's shape step: the authors' nuclear norm against the partial sum of singular values beyond K.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.spm_shape [--root DIR] [--jobs N] [--sequences a,b]
        [--smooth 300,1000] [--out DIR] [--rerun] [--no-progress]

SPM (:mod:`nrsfm.solvers.spm`) with ``shape_objective="nuclear"`` (its default, the authors' method) and
``"partial"`` (:func:`nrsfm.solvers.spm.shape_partial`) on every CMU file (or the synthetic stand-ins of
``benchmarks.classic`` without data) and on synthetic K = 3, 17-point sequences whose camera makes one steady
turn (``benchmarks.classic.long_sequence``; ``--smooth`` frame counts, each noise-free and with 1% noise): the
nuclear norm's minimum is not the shape on such a short arc. Each cell: object-frame e3D / camera error /
camera-frame e3D (time); "authors" the numbers of Dai et al.'s example script. Writes CSV/JSON/Markdown to
``runs/spm_shape``; cells are saved and resumed as in ``benchmarks.classic``.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from benchmarks.common import code_hash, markdown_table, run_cells_from_args, run_metadata, write_outputs

log = logging.getLogger("benchmarks.studies.spm_shape")

OBJECTIVES = ("nuclear", "partial")


def parse_frames(text: str) -> list[int]:
    """``"300,1000"``: frame counts >= 3 of the smooth-camera sequences ("" or "0": none)."""
    try:
        frames = [int(v) for v in text.split(",") if v.strip() and v.strip() != "0"]
    except ValueError:
        frames = [-1]
    if any(f < 3 for f in frames):
        raise ValueError(f"--smooth: expected comma-separated frame counts >= 3 (or 0 for none), got {text!r}")
    return frames


def run_one(job: str, objective: str) -> dict:
    """SPM with ``objective`` on one sequence: a row of ``benchmarks.classic.solve_cell``."""
    from benchmarks.classic import solve_cell

    return {**solve_cell(job, "spm", 0.0, "reference", {"shape_objective": objective}), "objective": objective}


def _cell(r: dict) -> str:
    if r["status"] != "ok":
        return f"not run: {r['why']}"
    obj = f"{r['e3d_object']:.4f}" if "e3d_object" in r else "–"
    cam = f"{r['rotation_error']:.4f}" if "rotation_error" in r else "–"
    return f"{obj} / {cam} / {r['e3d_camera']:.4f} ({r['seconds']:.1f} s)"


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import (SPM_REFERENCE, SPM_ROTATION_REFERENCE, data_where, job_identity,
                                    parse_data_benchmark)

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--smooth", default="300,1000,3000",
                       help="frame counts of the smooth-camera synthetic sequences (default 300,1000,3000; 0: none)")

    parsed = parse_data_benchmark("spm_shape", __doc__, argv, options=options,
                                  check=lambda args: parse_frames(args.smooth))
    if parsed is None:
        return 2
    args, folder, files, frames = parsed
    t0 = time.perf_counter()
    out = Path(args.out)
    jobs = [f"synthetic:{f}{noise}" for f in frames for noise in ("", ":0.01")] + files
    code = code_hash(__file__, Path(__file__).parent.parent / "classic.py")
    cells = [(f"{Path(j).stem if j.endswith('.mat') else j.replace(':', '-')}-{o}",
              {**job_identity(j), "objective": o, "code": code}, (j, o)) for j in jobs for o in OBJECTIVES]
    done = run_cells_from_args(args, cells, run_one, out, "spm_shape")
    if done is None:
        return 130
    rows, reused = done
    table = []
    for i in range(0, len(rows), len(OBJECTIVES)):
        pair = rows[i:i + len(OBJECTIVES)]
        name = pair[0]["sequence"]
        authors = (f"{SPM_REFERENCE[name][0]} ({SPM_REFERENCE[name][1]}) / {SPM_ROTATION_REFERENCE.get(name, '–')}"
                   if name in SPM_REFERENCE else "–")
        table.append([name, *(_cell(r) for r in pair), authors])
    md = markdown_table(["sequence", *(f"SPM, {o}" for o in OBJECTIVES), "authors"], table)
    where = data_where(folder, files)
    text = (f"### SPM's shape step: nuclear norm against the partial sum beyond K ({where}, smooth-camera "
            f"sequences of {', '.join(map(str, frames)) or 'no'} frames)\n\n"
            f"Each cell: object-frame e3D / camera error / camera-frame e3D (seconds).\n\n{md}\n")
    write_outputs(out, "spm_shape", text, rows, run_metadata(
        benchmark="spm shape", smooth=frames, jobs=args.jobs, data=str(folder or "stand-ins"), cells_reused=reused,
        wall_s=time.perf_counter() - t0))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
