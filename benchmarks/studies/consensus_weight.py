"""The weight of the ``consensus`` solver, chosen by leave-one-sequence-out on the CMU files.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.consensus_weight [--root DIR] [--jobs N] [--sequences a,b]
        [--methods empnd,pr] [--grid 0.5:1:0.05] [--missing 0.2] [--out DIR] [--rerun] [--no-progress]

Runs the two solvers of ``--methods`` once on every file under ``DIR/nrsfm``,
averages their camera-frame shapes with the first one's weight ``a`` and the
second's ``1 - a`` for every ``a`` of ``--grid``
(:func:`nrsfm.solvers.consensus.average_reconstructions`, as the solver does)
and scores each mean against the ground truth (camera-frame e3D). Then, for
each file, the weight is chosen on the *other* files alone: the ``a`` that
minimises the geometric mean over them of e3D(a) / e3D(a = 1), i.e. the gain
over the first solver alone. That file's e3D at that weight is its held-out
number; the weight chosen on all files is the one the solver's default should
be. Prints the table (with the best published e3D of NOTES.md) and writes
CSV/JSON/Markdown to ``runs/consensus_weight[-missingX]``. Without data (no
``--root``, ``$NRSFM_DATA`` unset) it runs on the synthetic stand-ins of
``benchmarks.classic``. One cell per sequence, saved and resumed as in
``benchmarks.classic``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import code_hash, config_hash, markdown_table, run_cells_from_args, run_metadata, write_outputs

log = logging.getLogger("benchmarks.studies.consensus_weight")


def parse_grid(text: str) -> list[float]:
    """``"0.5:1:0.05"`` (start:stop:step, both ends included) or ``"0.5,0.8,1"``: weights in [0, 1] that
    include 1 (the first solver alone, the reference of the gain)."""
    try:
        if ":" in text:
            lo, hi, step = (float(v) for v in text.split(":"))
            grid = list(np.round(np.arange(lo, hi + step / 2, step), 6)) if step > 0 else []
        else:
            grid = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        grid = []
    if not grid or any(not 0 <= a <= 1 for a in grid) or 1.0 not in grid:
        raise ValueError(f"--grid: expected weights in [0, 1] including 1, as 'start:stop:step' or a comma list, "
                         f"got {text!r}")
    return sorted(set(float(a) for a in grid))


def run_one(job: str, methods: tuple[str, str], grid: list[float], missing: float) -> dict:
    """Both solvers on one sequence and the e3D of every weighted mean; errors are recorded, never raised."""
    import nrsfm
    from benchmarks.classic import load_benchmark_sequence
    from nrsfm.datasets.synthetic import drop_entries
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d
    from nrsfm.solvers.consensus import average_reconstructions

    seq = drop_entries(load_benchmark_sequence(job), missing)
    row = {"sequence": seq.name, "frames": seq.n_frames, "points": seq.n_points, "missing": missing}
    recs = []
    for m in methods:
        try:
            recs.append(nrsfm.solve(seq, m))
        except NRSfMError as exc:
            return {**row, "status": "not run", "why": f"{m}: {exc}"}
    e3ds = [e3d(average_reconstructions(recs, [a, 1 - a])[0], seq.points_3d) for a in grid]
    return {**row, "status": "ok", "grid": grid, "e3d": e3ds, "seconds": [r.runtime_s for r in recs],
            "alone": [e3d(r.points_3d, seq.points_3d) for r in recs]}


def choose_weight(results: list[dict], grid: list[float]) -> int:
    """Index into ``grid`` of the weight minimising the geometric mean over ``results`` of e3D(a) / e3D(1)."""
    ratios = np.log([np.asarray(r["e3d"]) / r["e3d"][grid.index(1.0)] for r in results])  # (files, grid)
    return int(np.argmin(ratios.mean(axis=0)))


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import REFERENCE, data_where, job_identity, parse_data_benchmark
    from nrsfm.solvers import get_solver

    def options(p: argparse.ArgumentParser) -> None:
        p.add_argument("--methods", default="empnd,pr", help="the two solvers averaged (default: empnd,pr)")
        p.add_argument("--grid", default="0.5:1:0.05", help="weights of the first solver (default 0.5:1:0.05)")
        p.add_argument("--missing", type=float, default=0.0, help="fraction of entries to mark missing (fixed seed)")

    def check(args: argparse.Namespace) -> tuple[tuple[str, ...], list[float]]:
        methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
        if len(methods) != 2:
            raise ValueError(f"--methods: expected two comma-separated solvers, got {args.methods!r}")
        for m in methods:
            get_solver(m)
        grid = parse_grid(args.grid)
        if not 0 <= args.missing < 1:
            raise ValueError(f"--missing: expected a fraction in [0, 1), got {args.missing}")
        return methods, grid

    parsed = parse_data_benchmark("consensus_weight", __doc__, argv, jobs_help="parallel sequences (joblib)",
                                  options=options, check=check,
                                  out_help="output folder (default: runs/consensus_weight[-missingX])")
    if parsed is None:
        return 2
    args, folder, files, (methods, grid) = parsed
    t0 = time.perf_counter()
    out = Path(args.out or f"runs/consensus_weight{'-missing' + str(args.missing) if args.missing else ''}")
    code = code_hash(__file__, Path(__file__).parent.parent / "classic.py")
    key = {"methods": methods, "grid": grid, "missing": args.missing}
    cells = [(f"{Path(f).stem}-{config_hash(key)}", {**job_identity(f), **key, "code": code},
              (f, methods, grid, args.missing)) for f in files]
    done = run_cells_from_args(args, cells, run_one, out, "consensus_weight")
    if done is None:
        return 130
    results, reused = done
    ok = [r for r in results if r["status"] == "ok"]
    for r in results:
        if r["status"] != "ok":
            log.warning("%s: not run: %s", r["sequence"], r["why"])
    if len(ok) < 2:
        print("consensus_weight: error: fewer than two sequences solved; nothing to leave out", file=sys.stderr)
        return 1
    whole = choose_weight(ok, grid)
    table, rows = [], []
    for r in ok:
        held = choose_weight([o for o in ok if o is not r], grid)
        published = [v[0] for v in REFERENCE.get(r["sequence"], {}).values()]
        best_pub = min(published) if published else None
        e = r["e3d"]
        table.append([r["sequence"], *(f"{v:.5f}" for v in e), f"{grid[held]:g}", f"{e[held]:.5f}",
                      f"{best_pub:.4f}" if best_pub is not None else "–"])
        rows.append({"sequence": r["sequence"], "held_out_weight": grid[held], "held_out_e3d": e[held],
                     "e3d_first_alone": r["alone"][0], "e3d_second_alone": r["alone"][1],
                     "e3d_at_whole_set_weight": e[whole], "best_published": best_pub,
                     "seconds_first": r["seconds"][0], "seconds_second": r["seconds"][1],
                     **{f"e3d_a{a:g}": v for a, v in zip(grid, e)}})
    md = markdown_table(["sequence", *(f"a = {a:g}" for a in grid), "held-out a", "held-out e3D",
                         "best published"], table)
    where = data_where(folder, files)
    text = (f"### Consensus weight: camera-frame e3D of a * {methods[0]} + (1 - a) * {methods[1]} ({where}, "
            f"{100 * args.missing:.0f}% missing)\n\n{md}\n\nWeight chosen on all files: a = {grid[whole]:g} "
            f"(the held-out column chooses it on the other files only).\n")
    write_outputs(out, "consensus_weight", text, rows, run_metadata(
        benchmark="consensus weight", methods=list(methods), grid=grid, missing=args.missing, jobs=args.jobs,
        data=str(folder or "stand-ins"), whole_set_weight=grid[whole], cells_reused=reused))
    print(f"wrote {out}/consensus_weight.md, consensus_weight.csv, consensus_weight.json "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
