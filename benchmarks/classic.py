"""The classic NRSfM benchmark: every registered solver on every CMU sequence.

    python -m benchmarks.classic [--root DIR] [--jobs N] [--methods a,b] [--missing 0.2] [--long 3000] [--out DIR]
                                 [--rerun] [--no-progress]

Reads every `.mat` under ``DIR/nrsfm`` (default ``$NRSFM_DATA/nrsfm``; Akhter
and PND layouts), solves each with every registered solver (in parallel over the
(sequence, solver) cells with joblib; per-sequence seeds come from the
sequence name, so results do not depend on ``--jobs``), and prints one Markdown table: per
sequence and method the e3D in the camera frame, the e3D in the object frame
(where the ground truth has a world frame), the camera error of Akhter et al.
(:func:`nrsfm.metrics.rotation_error`, same files), the normalised error and the run
time, with the reference numbers of the authors' code (NOTES.md) beside them.
``--missing 0.2`` marks that fraction of entries missing (fixed seed) first.
Every solver runs at its automatic defaults (``--settings auto``, the default: what a user
gets); ``--settings reference`` applies the per-sequence settings that reproduce the
reference numbers (:data:`REFERENCE_SETTINGS`).
``--long 3000`` adds a synthetic 3000-frame, 17-point sequence (the speed
target: 120 s per solver; drink's is 60 s) and a speed table.
Also written as CSV and JSON, with a plot of every e3D beside the best
published one and of every solve's time (``classic.png``). With no ``--root``
and ``$NRSFM_DATA`` unset it runs on CMU-sized synthetic stand-ins
(:data:`STAND_INS`), so a fresh clone without the data runs it too.

Every cell's result is saved under ``OUT/cells`` as soon as it is solved, and a
later run with the same output folder reuses the saved cells whose input file,
settings and code (:func:`benchmarks.common.code_hash`) are unchanged: an
interrupted run resumes where it stopped, and adding a method or a sequence
solves only the new cells. ``--rerun`` solves everything again (the times in
the table are those of the run that solved each cell). A progress bar on stderr
counts the cells (``--no-progress`` hides it).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

from nrsfm.datasets.synthetic import drop_entries

from benchmarks.common import (add_run_arguments, code_hash, markdown_table, run_cells_from_args, run_metadata,
                               worker_count,
                               write_csv, write_json)

log = logging.getLogger("benchmarks.classic")

#: Reference numbers (NOTES.md): authors' code in Octave on 2 cores. Per sequence and method:
#: (e3D camera frame, e3D object frame or None, normalised error, seconds).
REFERENCE = {
    "drink": {"PTA": (.0233, .0250, .0154, 20), "CSF2": (.0168, .0197, .0115, 87), "EM-PND2": (.0048, None, .0031, 742)},
    "pickup": {"PTA": (.0693, .2369, .0415, 3), "CSF2": (.0256, .2248, .0170, 49),
               "EM-PND2": (.0193, None, .0132, 291)},
    "yoga": {"PTA": (.0516, .1629, .0379, 4), "CSF2": (.0303, .1479, .0212, 54), "EM-PND2": (.0169, None, .0128, 279)},
    "stretch": {"PTA": (.0833, .1088, .0567, 3), "CSF2": (.0393, .0712, .0246, 48),
                "KSTA": (.0572, .0839, .0336, 446), "EM-PND2": (.0222, None, .0149, 299)},
    "dance": {"PTA": (.2957, None, .2478, 1), "CSF2": (.2681, None, .1933, 117), "KSTA": (.1796, None, .1290, 202),
              "EM-PND2": (.1567, None, .1247, 787)},
    "walking": {"PTA": (.6012, None, .3054, 3), "CSF2": (.1857, None, .1233, 51), "KSTA": (.1038, None, .0681, 91),
                "EM-PND2": (.0597, None, .0407, 354)},
    "face": {"PTA": (.0444, None, .0299, 2), "CSF2": (.0363, None, .0254, 31), "KSTA": (.0337, None, .0227, 101),
             "EM-PND2": (.0211, None, .0150, 158)},
    "jaws_rearranged": {"PTA": (.2497, None, .1560, 0.5), "CSF2": (.0081, None, .0037, 0.2),
                        "EM-PND2": (.0550, None, .0272, 892)},
}
#: SPM (Dai et al.) from its authors' own run: object frame for the Akhter sequences, camera frame otherwise.
SPM_REFERENCE = {"drink": (".0266", "object"), "pickup": (".1731", "object"), "yoga": (".1150", "object"),
                 "stretch": (".1034", "object"), "dance": (".1864", "camera"), "face": (".0303", "camera"),
                 "walking": (".1298", "camera"), "jaws_rearranged": (".2357", "camera")}
#: The camera error (:func:`nrsfm.metrics.rotation_error`, Akhter et al.'s metric) of the same SPM runs, from the
#: header of the authors' example script (``Rotation_Err``), for the files with ground-truth cameras.
SPM_ROTATION_REFERENCE = {"drink": ".0071", "pickup": ".1210", "yoga": ".0883", "stretch": ".0676"}
#: Per-sequence settings that reproduce the reference numbers (``--settings reference``), keyed by
#: the benchmark's file names. They belong to this benchmark, never to a solver's defaults (which do not look at
#: names). CSF2: K from a K sweep against the reference cells (d = ceil(0.1 F), its default; the authors set K by
#: hand). SPM: the authors' K per sequence (Dai et al.'s example scripts). ``--settings auto`` runs every solver
#: with its automatic defaults instead.
REFERENCE_SETTINGS = {
    "csf2": {"drink": {"K": 10}, "pickup": {"K": 10}, "yoga": {"K": 8}, "stretch": {"K": 8}, "dance": {"K": 2},
             "jaws_rearranged": {"K": 3}},
    "spm": {"drink": {"K": 12}, "pickup": {"K": 12}, "yoga": {"K": 10}, "stretch": {"K": 11}, "dance": {"K": 10},
            "face": {"K": 7}, "walking": {"K": 8}, "jaws_rearranged": {"K": 4}},
}
#: The one method declared in advance as "ours" against the best published numbers (no per-file choice).
DECLARED = "consensus"
#: Which reference row a registered solver is compared with.
SOLVER_REFERENCE = {"csf2": "CSF2", "empnd": "EM-PND2", "spm": "SPM", "pta": "PTA", "ksta": "KSTA"}


def long_sequence(n_frames: int, noise: float = 0.0):
    """The speed case of the issue: a synthetic ``n_frames`` x 17-point low-rank (K = 3) sequence, smooth cameras
    (one steady turn), noise-free unless ``noise`` (2D noise, relative)."""
    from nrsfm.datasets.synthetic import lowrank_sequence

    name = f"synthetic-{n_frames}x17" + (f"-noise{noise:g}" if noise else "")
    return lowrank_sequence(n_frames, 17, 3, cameras="smooth", seed=0, noise=noise, name=name)


#: The stand-ins used when no CMU data is found (no ``--root``, ``$NRSFM_DATA`` unset), so that a fresh clone
#: runs the benchmark: CMU-sized sequences generated by :mod:`nrsfm.datasets.synthetic`.
STAND_INS = ("synthetic-lowrank-300x41", "synthetic-face-300x68")


def stand_in(name: str):
    """One of :data:`STAND_INS`: a K = 5 low-rank sequence with random cameras and 0.5% 2D noise (drink-sized
    points), or the synthetic face (68 landmarks, head rotations)."""
    from nrsfm.datasets.synthetic import face_sequences, lowrank_sequence

    if name == STAND_INS[0]:
        return lowrank_sequence(300, 41, 5, noise=0.005, cameras="random", seed=0, name=name)
    if name == STAND_INS[1]:
        return face_sequences(1, 300)[0].replace(name=name)
    raise ValueError(f"stand-in: expected one of {STAND_INS}, got {name!r}")


def benchmark_sequences(root: str | None, sequences: str | None, who: str) -> tuple[Path | None, list[str]]:
    """The sequences a benchmark runs: the `.mat` files under ``root/nrsfm`` (``$NRSFM_DATA`` when ``root`` is
    None) or, with neither, the names of :data:`STAND_INS`; narrowed to the comma-separated ``sequences``.

    Returns:
        The data folder (None for the stand-ins) and the jobs for :func:`load_benchmark_sequence`.

    Raises:
        NRSfMError / ValueError: a named folder that does not exist or holds no files, an unknown sequence name.
    """
    from nrsfm.datasets import find_dataset, list_cmu_sequences
    from nrsfm.datasets.paths import data_root

    folder = find_dataset("nrsfm", root, required=root is not None or data_root() is not None)
    if folder is None:
        log.info("%s: no CMU data ($NRSFM_DATA is not set and no --root): running on the synthetic stand-ins %s; "
                 "pass --root DIR for the CMU files", who, ", ".join(STAND_INS))
        files = list(STAND_INS)
    else:
        files = [str(f) for f in list_cmu_sequences(folder)]
        if not files:
            raise ValueError(f"{folder}: expected CMU sequence files (.mat), found none; point --root or "
                             "$NRSFM_DATA at the folder holding nrsfm/")
    if sequences:
        want = [s.strip() for s in sequences.split(",") if s.strip()]
        names = [Path(f).stem for f in files]
        unknown = [w for w in want if w not in names]
        if unknown:
            raise ValueError(f"--sequences: expected names among {names}, got {', '.join(unknown)}")
        files = [f for f, n in zip(files, names) if n in want]
    return folder, files


def _non_negative(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def data_where(folder: Path | None, files: list[str]) -> str:
    """What a benchmark ran on, for its table's title: the CMU files, or the stand-ins."""
    return f"{len(files)} CMU files" if folder is not None else "synthetic stand-ins, no CMU data"


def add_data_arguments(parser: argparse.ArgumentParser, jobs_help: str) -> None:
    """The ``--root``, ``--jobs`` and ``--sequences`` options of the benchmarks over the CMU files (read with
    :func:`benchmark_sequences`)."""
    parser.add_argument("--root", help="data folder holding nrsfm/ (default: $NRSFM_DATA; neither: synthetic "
                                       "stand-ins)")
    parser.add_argument("--jobs", type=worker_count, default=1, help=jobs_help)
    parser.add_argument("--sequences", default=None, help="comma-separated sequence names (default: all files)")


def parse_data_benchmark(name: str, doc: str, argv: list[str] | None, *, jobs_help: str = "parallel cells (joblib)",
                         options: Callable[[argparse.ArgumentParser], None] | None = None,
                         check: Callable[[argparse.Namespace], Any] | None = None, out_help: str | None = None
                         ) -> tuple[argparse.Namespace, Path | None, list[str], Any] | None:
    """The command line of ``python -m benchmarks.NAME`` over the CMU files: :func:`add_data_arguments`, the
    script's ``options``, ``--out`` (default ``runs/NAME``; None when ``out_help`` describes another default),
    ``--rerun`` and ``--no-progress``; INFO logging on stderr; then ``check(args)`` (raises ValueError on a bad
    option; what it returns is passed on) and :func:`benchmark_sequences`.

    Returns:
        ``(args, folder, files, checked)``, or None after printing ``NAME: error: ...`` on stderr (exit status 2).
    """
    from nrsfm.errors import NRSfMError

    p = argparse.ArgumentParser(prog=f"python -m benchmarks.{name}", description=doc.split("\n\n")[0])
    add_data_arguments(p, jobs_help)
    if options is not None:
        options(p)
    p.add_argument("--out", default=None if out_help else f"runs/{name}",
                   help=out_help or f"output folder (default: runs/{name})")
    add_run_arguments(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    try:
        checked = check(args) if check is not None else None
        folder, files = benchmark_sequences(args.root, args.sequences, name)
    except (NRSfMError, ValueError) as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return None
    return args, folder, files, checked


def load_benchmark_sequence(job: str):
    """A job of :func:`benchmark_sequences` (a file or a stand-in name), or ``synthetic:F`` /
    ``synthetic:F:NOISE`` for :func:`long_sequence`, as a :class:`~nrsfm.sequence.Sequence`."""
    import nrsfm

    if job.startswith("synthetic:"):
        _, frames, *noise = job.split(":")
        return long_sequence(int(frames), float(noise[0]) if noise else 0.0)
    if job in STAND_INS:
        return stand_in(job)
    return nrsfm.load_sequence(job)


def solve_cell(job: str, method: str, missing: float, settings: str = "auto", extra: dict | None = None
               ) -> dict:
    """One solver on one sequence (a file, ``synthetic:F`` for :func:`long_sequence` or a name in
    :data:`STAND_INS`): one result row (errors recorded, never raised). ``settings="reference"`` applies
    :data:`REFERENCE_SETTINGS`; ``extra`` sets more parameters (over those)."""
    import nrsfm
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import classic_metrics

    seq = drop_entries(load_benchmark_sequence(job), missing)
    row = {"sequence": seq.name, "method": method, "frames": seq.n_frames, "points": seq.n_points,
           "missing": missing}
    overrides = {}
    if settings == "reference":
        # EM-PND needs none: with missing points it starts from CSF2 with its rank-rule K (the e3D after EM is
        # the same as from CSF2's reference K; benchmarks/RESULTS.md), with complete tracks from its own start
        overrides = dict(REFERENCE_SETTINGS.get(method, {}).get(seq.name, {}))
    overrides.update(extra or {})
    row["settings"] = ",".join(f"{k}={v}" for k, v in overrides.items()) or "default"
    t0 = time.perf_counter()
    try:
        rec = nrsfm.solve(seq, method, **overrides)
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc), "seconds": time.perf_counter() - t0}
    # the numbers of `nrsfm solve`: object frame and camera error only against a moving ground-truth camera
    metrics = classic_metrics(rec.points_3d, seq.points_3d, pred_rotations=rec.rotations,
                              gt_rotations=seq.camera_rotations)
    row.update(status="ok", seconds=rec.runtime_s, iterations=rec.iterations, converged=rec.converged,
               e3d_camera=metrics["e3d"], normalized_error=metrics["normalized_error"])
    row.update({key: metrics[key] for key in ("e3d_object", "rotation_error") if key in metrics})
    return row


def job_identity(job: str) -> dict:
    """What a cached result of ``job`` depends on besides the code: a file's path and the SHA-1 of its bytes (a
    changed file is solved again), or the name of a generated sequence."""
    import hashlib

    path = Path(job)
    if job.startswith("synthetic:") or job in STAND_INS or not path.is_file():
        return {"job": job}
    return {"job": str(path.resolve()), "sha1": hashlib.sha1(path.read_bytes()).hexdigest()}


def main(argv: list[str] | None = None) -> int:
    from nrsfm.errors import NRSfMError
    from nrsfm.solvers import available_solvers

    p = argparse.ArgumentParser(prog="python -m benchmarks.classic", description=__doc__.split("\n\n")[0])
    add_data_arguments(p, "parallel sequences (joblib)")
    p.add_argument("--methods", default=None, help="comma-separated solvers (default: all registered but rank3)")
    p.add_argument("--missing", type=float, default=0.0, help="fraction of entries to mark missing (fixed seed)")
    p.add_argument("--long", type=_non_negative, default=3000,
                   help="also time every solver on a synthetic LONG x 17-point sequence (0: skip)")
    p.add_argument("--settings", choices=("auto", "reference"), default="auto",
                   help="every solver's automatic defaults (default), or the per-sequence settings that reproduce "
                        "the reference numbers")
    p.add_argument("--out", default=None, help="output folder (default: runs/classic[-missingX])")
    add_run_arguments(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    try:
        folder, files = benchmark_sequences(args.root, args.sequences, "classic")
        methods = [m for m in available_solvers() if m != "rank3"] if args.methods is None else \
            [m.strip() for m in args.methods.split(",")]
        for m in methods:
            if m not in available_solvers():
                raise ValueError(f"--methods: expected names among {available_solvers()}, got {m!r}")
        if not 0 <= args.missing < 1:
            raise ValueError(f"--missing: expected a fraction in [0, 1), got {args.missing}")
    except (NRSfMError, ValueError) as exc:
        print(f"classic: error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    log.info("classic: %d sequences x %s, missing %.0f%%, %d jobs", len(files), methods, 100 * args.missing,
             args.jobs)
    out = Path(args.out or f"runs/classic{'-missing' + str(args.missing) if args.missing else ''}")
    jobs = ([f"synthetic:{args.long}"] if args.long > 0 else []) + files  # the longest first
    code = code_hash(__file__)
    identity = {j: job_identity(j) for j in jobs}  # a file's hash once, not once per method
    cells = [(f"{Path(j).stem if j.endswith('.mat') else j.replace(':', '-')}-{m}",
              {**identity[j], "method": m, "missing": args.missing, "settings": args.settings, "code": code},
              (j, m, args.missing, args.settings)) for j in jobs for m in methods]
    done = run_cells_from_args(args, cells, solve_cell, out, "classic")
    if done is None:
        return 130
    rows, reused = done
    per_seq = [rows[i:i + len(methods)] for i in range(0, len(rows), len(methods))]
    table, verdicts = [], []
    for rs in per_seq:
        name = rs[0]["sequence"]
        ref = REFERENCE.get(name, {})
        best_pub = min((v[0] for v in ref.values()), default=None)
        for r in rs:
            refkey = SOLVER_REFERENCE.get(r["method"])
            rv = ref.get(refkey) if refkey else None
            refcell = "–"
            if refkey == "SPM" and name in SPM_REFERENCE:
                refcell = f"{SPM_REFERENCE[name][0]} ({SPM_REFERENCE[name][1]})"
                if name in SPM_ROTATION_REFERENCE:
                    refcell += f"; camera err. {SPM_ROTATION_REFERENCE[name]}"
            elif rv:
                refcell = f"{rv[0]:.4f}" + (f" [{rv[1]:.4f}]" if rv[1] is not None else "") + f" / {rv[2]:.4f}"
            if r["status"] != "ok":
                table.append([name, r["method"], f"not run: {r['why']}", "", "", "", f"{r['seconds']:.1f}", refcell,
                              ""])
                continue
            label = r["method"] + (f" ({r['settings']})" if r["settings"] != "default" else "")
            table.append([name, label, f"{r['e3d_camera']:.4f}",
                          f"{r['e3d_object']:.4f}" if "e3d_object" in r else "–",
                          f"{r['rotation_error']:.4f}" if "rotation_error" in r else "–",
                          f"{r['normalized_error']:.4f}",
                          f"{r['seconds']:.1f}", refcell, f"{rv[3]:g}" if rv else "–"])
        ok = [r for r in rs if r["status"] == "ok"]
        if ok and best_pub is not None:
            best = min(ok, key=lambda r: r["e3d_camera"])
            declared = next((r for r in ok if r["method"] == DECLARED), None)
            verdicts.append([name, f"{declared['e3d_camera']:.4f}" if declared else "not run",
                             "yes" if declared and declared["e3d_camera"] < best_pub else "no",
                             best["method"], f"{best['e3d_camera']:.4f}", f"{best_pub:.4f}",
                             "yes" if best["e3d_camera"] < best_pub else "no"])
    header = ["sequence", "method", "e3D camera", "e3D object", "camera err.", "norm. error", "time (s)",
              "reference e3D cam [obj] / NE", "ref. time (s)"]
    where = folder if folder is not None else "synthetic stand-ins, no CMU data"
    text = [f"### Classic NRSfM benchmark ({where}, {100 * args.missing:.0f}% missing), e3D and normalised error "
            f"(camera frame unless stated), {os.cpu_count()} CPU cores\n", markdown_table(header, table)]
    if reused:
        text.append(f"\n{reused} of {len(cells)} cells were reused from an earlier run saved in {out / 'cells'}, with "
                    "the times measured then (`--rerun` solves every cell again).")
    limits = {"drink": 60.0, f"synthetic-{args.long}x17": 120.0}
    speed = [[r["sequence"], r["method"], f"{r['seconds']:.1f}", f"{limits[r['sequence']]:.0f}",
              "yes" if r["seconds"] <= limits[r["sequence"]] else "no"]
             for r in rows if r["sequence"] in limits and r["status"] == "ok"]
    if speed:
        text += [f"\nSpeed targets (limits for 2 CPU cores; this machine has {os.cpu_count()}; jobs run side by "
                 "side share them):\n",
                 markdown_table(["sequence", "method", "time (s)", "limit (s)", "within"], speed)]
    if verdicts:
        text += [f"\nAgainst the best published camera-frame e3D (the authors' code; NOTES.md): the pre-declared "
                 f"method ({DECLARED}) and, as an oracle, the best of ours per file picked with the ground truth:\n",
                 markdown_table(["sequence", f"{DECLARED} e3D", f"{DECLARED} better", "oracle: best of ours", "e3D",
                                 "best published", "oracle better"], verdicts)]
    print("\n".join(text))
    total = time.perf_counter() - t0
    meta = run_metadata(benchmark="classic NRSfM",
                        metric="e3D (camera/object frame), camera error (Akhter et al.), normalised error",
                        data=str(where), methods=methods, missing=args.missing, jobs=args.jobs,
                        settings=args.settings, cells_reused=reused,
                        total_seconds=total)
    write_csv(out / "classic.csv", rows)
    write_json(out / "classic.json", {"meta": meta, "rows": rows})
    (out / "classic.md").write_text("\n".join(text) + "\n")
    plot_results(rows, out / "classic.png")
    print(f"\nwrote {out}/classic.md, classic.csv, classic.json, classic.png ({total:.0f} s)")
    return 0


def plot_results(rows: list[dict], path: Path) -> None:
    """Grouped bars per sequence (rows with ``sequence``, ``method``, ``status``, ``e3d_camera``, ``seconds``;
    ``benchmarks.studies.pr_sweep`` passes its configurations as methods): each solver's camera-frame e3D (log scale;
    the best published e3D of :data:`REFERENCE` as a black tick) and its time. Solvers that did not run leave
    a gap."""
    from nrsfm.plotting import _pyplot, _save

    plt = _pyplot()
    seqs = list(dict.fromkeys(r["sequence"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["sequence"], r["method"]): r for r in rows if r["status"] == "ok"}
    x = np.arange(len(seqs))
    width = 0.8 / max(len(methods), 1)
    label_width = 0.055 * max(len(m) for m in methods + ["best published"])  # inches, for the legend
    fig, axes = plt.subplots(2, 1, figsize=(max(4.0, 1.3 * len(seqs) + 1.5) + label_width, 6.0), sharex=True)
    for i, m in enumerate(methods):
        pos = x - 0.4 + width * (i + 0.5)
        for ax, key in zip(axes, ("e3d_camera", "seconds")):
            ax.bar(pos, [cell[(s, m)][key] if (s, m) in cell else np.nan for s in seqs], width, label=m)
    best = [min((v[0] for v in REFERENCE.get(s, {}).values()), default=np.nan) for s in seqs]
    axes[0].scatter(x, best, marker="_", s=900, c="k", zorder=3, label="best published")
    shown = np.array([r["e3d_camera"] for r in cell.values()] + best, dtype=float)
    if (shown[np.isfinite(shown)] > 0).any():  # log scale needs a positive value (exact solves give 0)
        axes[0].set_yscale("log", nonpositive="clip")
    axes[0].set_ylabel("e3D (camera frame)")
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), markerscale=0.3)
    axes[1].set_ylabel("time per solve (s)")
    axes[1].set_xticks(x, seqs, fontsize=7, rotation=15)
    _save(fig, path, overwrite=True)


if __name__ == "__main__":
    sys.exit(main())
