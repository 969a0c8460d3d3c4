"""Every solver at its default settings beside its best fixed K, on the tuning set, a validation set and a test set.

    OMP_NUM_THREADS=1 python -m benchmarks.defaults [--set validation|test|holdout|cmu] [--root DIR] [--jobs N]
        [--methods a,b] [--missing 0,0.2] [--fill auto|reference|lowrank] [--k-max 12] [--out DIR] [--rerun]
        [--no-progress]

The library's defaults (CSF2's and SPM's automatic K, the consensus weights, EM-PPCA's K, PR's regulariser)
were chosen on the CMU files (``--set cmu``, the tuning set). The validation set (``--set validation``,
the default) is motion nobody tuned them on, :data:`VALIDATION`: 300 frames (30 s at 10 fps) of Human3.6M
training subjects (S1, S5-S8), 17 joints, seen by an orthographic camera
that turns steadily by 30-120 degrees about the vertical axis (:func:`nrsfm.datasets.synthetic.orbit_sequence`),
plus two synthetic faces. Without Human3.6M the motions are the synthetic humans' (same turns). The test set
(``--set test``, :data:`TEST`) is held out from every choice, the validation set's included: the five actions the
validation set does not use, each on two of the training subjects, turns of 30-120 degrees, and two other faces.
The second held-out set (``--set holdout``, :data:`HOLDOUT`) was declared after the test set had informed a choice:
subject S9 (a Human3.6M test subject, unused by every other set) in all 15 actions, and two more faces.

Each solver runs at its defaults (K = 0 where it has a K); CSF2, SPM and EM-PPCA also at every fixed K from
1 to ``--k-max`` that fits the sequence (3K < min(2F, P); K <= 5 on 17 joints). The table gives the camera-frame
e3D at the default, the best fixed K (an oracle: chosen with the ground truth) and their ratio; the summary
counts the sequences where the default is within 10% of that oracle. ``--missing 0,0.2`` runs every cell also
with 20% of the entries missing (fixed seed). CSF2 and SPM complete missing points as their ``fill`` parameter
says: by default (``--fill auto``) the automatic K solves every K on the tracks EM-PND's reconstruction completes,
while each fixed K completes them at rank 3K; ``--fill reference`` completes them by EM-PND's reconstruction at
every fixed K too (the oracle of the automatic K's own path), ``--fill lowrank`` at rank 3K everywhere. Cells are
saved and resumed as in ``benchmarks.classic``; outputs in ``runs/defaults-SET``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from benchmarks.common import (code_hash, markdown_table, parse_fractions, parse_study_arguments, run_cells_from_args,
                               run_metadata, write_outputs)

log = logging.getLogger("benchmarks.defaults")

#: The validation motions: (Human3.6M training subject, action (its first sub-action file by name), turn of the
#: camera in degrees).
VALIDATION = (("S1", "Walking", 30), ("S1", "Eating", 120), ("S5", "Directions", 60), ("S5", "Phoning", 90),
              ("S6", "Greeting", 45), ("S6", "SittingDown", 105), ("S7", "Discussion", 75), ("S7", "WalkDog", 120),
              ("S8", "Posing", 30), ("S8", "Smoking", 90))
#: The test motions, held out from every choice: the five Human3.6M actions :data:`VALIDATION` does not use (in
#: alphabetical order), each on two training subjects (the i-th action on the i-th and (i + 2 mod 5)-th of S1, S5-S8),
#: turns 30-120 degrees in steps of 10 in that order.
TEST = (("S1", "Photo", 30), ("S6", "Photo", 40), ("S5", "Purchases", 50), ("S7", "Purchases", 60),
        ("S6", "Sitting", 70), ("S8", "Sitting", 80), ("S7", "Waiting", 90), ("S1", "Waiting", 100),
        ("S8", "WalkTogether", 110), ("S5", "WalkTogether", 120))
#: A second held-out set, declared after the test set had been looked at (:mod:`nrsfm.solvers.kselect`'s depth-flip
#: guard was chosen on the validation and test sets): subject S9, unused elsewhere, in each of the 15 Human3.6M
#: actions in alphabetical order, turns 30-120 degrees in steps of 15 in that order, repeated.
HOLDOUT = tuple(("S9", a, 30 + 15 * (i % 7)) for i, a in enumerate((
    "Directions", "Discussion", "Eating", "Greeting", "Phoning", "Photo", "Posing", "Purchases", "Sitting",
    "SittingDown", "Smoking", "Waiting", "WalkDog", "WalkTogether", "Walking")))
#: The synthetic humans' motions standing in for :data:`VALIDATION`'s and :data:`TEST`'s without Human3.6M, in
#: order (the test set's starting at the fourth).
STAND_IN_MOTIONS = ("walking", "sitting_down", "reaching", "bending", "turning", "waving")
#: Two synthetic faces (300 frames each; the classic benchmark's stand-in face is the first of the generator, not
#: used here) in the validation set, two others in the test set.
FACES = (1, 2)
TEST_FACES = (3, 4)
HOLDOUT_FACES = (5, 6)
N_FRAMES = 300
#: Solvers with a number of basis shapes ``K`` (0: automatic), swept over fixed K.
WITH_K = ("csf2", "spm", "emppca")
#: Solvers with a ``fill`` parameter (how missing points are completed; ``--fill``).
WITH_FILL = ("csf2", "spm")


def validation_jobs(root: str | None, which: str = "validation") -> tuple[Path | None, list[str]]:
    """The validation sequences (``which="test"`` / ``"holdout"``: the test / hold-out sequences) as jobs for
    :func:`load_job`:
    ``h36m:ROOT:SUBJECT:ACTION:TURN`` when Human3.6M is found under ``root`` (or ``$NRSFM_DATA``), else
    ``human:SUBJECT:MOTION:TURN`` stand-ins; then ``face:I``."""
    from nrsfm.datasets import find_dataset
    from nrsfm.datasets.paths import data_root

    sets = {"validation": (VALIDATION, FACES, 0), "test": (TEST, TEST_FACES, 3),
            "holdout": (HOLDOUT, HOLDOUT_FACES, 0)}
    if which not in sets:
        raise ValueError(f"expected the set 'validation', 'test' or 'holdout', got {which!r}")
    motions, faces, shift = sets[which]
    folder = find_dataset("h36m", root, required=False) if (root or data_root()) else None
    if folder is not None:
        jobs = [f"h36m:{folder}:{s}:{a}:{t}" for s, a, t in motions]
    else:
        log.info("defaults: no Human3.6M data: the %s motions are the synthetic humans'", which)
        jobs = [f"human:{s}:{STAND_IN_MOTIONS[(i + shift) % len(STAND_IN_MOTIONS)]}:{t}"
                for i, (s, _, t) in enumerate(motions)]
    return folder, jobs + [f"face:{i}" for i in faces]


def study_over_both_sets(name: str, doc: str, argv: list[str] | None,
                         options: Callable[[argparse.ArgumentParser], None]):
    """The command line of a study over the CMU files and the validation set (:func:`benchmarks.common.
    parse_study_arguments`; ``options`` must add ``--missing``): the arguments, the ``--missing`` fractions, and
    (data folder, jobs) of the CMU files (the tuning set; stand-ins without data) and of the validation set. A bad
    value is printed as ``NAME: error: ...`` on stderr and None returned (exit status 2)."""
    from nrsfm.errors import NRSfMError

    from benchmarks.classic import benchmark_sequences

    args = parse_study_arguments(name, doc, argv, options)
    try:
        return (args, parse_fractions(args.missing, "--missing"), benchmark_sequences(args.root, None, name),
                validation_jobs(args.root))
    except (NRSfMError, ValueError) as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return None


def job_label(job: str) -> str:
    """A job's name in tables and cache keys: a file's stem, or a generated job without its data folder
    (``h36m-S1-Walking-30``)."""
    return Path(job).stem if Path(job).is_file() else job.rsplit("/", 1)[-1].replace(":", "-")


def load_job(job: str):
    """A validation job of :func:`validation_jobs`, or a job of :func:`benchmarks.classic.benchmark_sequences` (a CMU
    file or a stand-in name), as a :class:`~nrsfm.sequence.Sequence`."""
    from nrsfm.datasets import h36m
    from nrsfm.datasets.synthetic import face_sequences, human_motion, orbit_sequence

    kind, _, rest = job.partition(":")
    if kind == "h36m":
        root, subject, action, turn = rest.rsplit(":", 3)
        stems = [a for a in h36m.list_actions(root, subject) if h36m.action_of(a) == action]
        if not stems:
            raise FileNotFoundError(f"{root}/{subject}: no sub-action of {action} "
                                    f"(known: {h36m.list_actions(root, subject)})")
        stride = h36m.detect_stride(root, subject)
        world = h36m.load_h36m_world(root, subject, min(stems), stride=stride)[:N_FRAMES]
        return orbit_sequence(world, float(turn), up=2, name=f"h36m-{subject}-{action}-turn{turn}",
                              joint_names=h36m.JOINT_NAMES, edges=np.array(h36m.EDGES), fps=10.0)
    if kind == "human":
        subject, motion, turn = rest.split(":")
        world = human_motion(subject, motion, N_FRAMES, 10.0, seed=7)
        return orbit_sequence(world, float(turn), up=1, name=f"human-{subject}-{motion}-turn{turn}",
                              joint_names=h36m.JOINT_NAMES, edges=np.array(h36m.EDGES), fps=10.0)
    if kind == "face":
        i = int(rest)
        return face_sequences(i + 1, N_FRAMES)[i].replace(name=f"face-{i}")
    from benchmarks.classic import load_benchmark_sequence

    return load_benchmark_sequence(job)


def k_cap(n_frames: int, n_points: int, k_max: int) -> int:
    """The largest fixed K swept: at most ``k_max`` with 3K < min(2F, P)."""
    return max(1, min(k_max, (min(2 * n_frames, n_points) - 1) // 3))


def run_cell(job: str, method: str, k: int | None, missing: float, fill: str = "auto") -> dict:
    """One solver on one sequence: ``k`` None for its defaults, else that fixed K; ``fill`` other than ``"auto"``
    only for the solvers of :data:`WITH_FILL`. Errors are recorded."""
    import nrsfm
    from nrsfm.datasets.synthetic import drop_entries
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d

    seq = drop_entries(load_job(job), missing)
    filled = {} if fill == "auto" else {"fill": fill}
    row = {"sequence": seq.name, "method": method, "K": "default" if k is None else k, "missing": missing, **filled}
    t0 = time.perf_counter()
    try:
        rec = nrsfm.solve(seq, method, **({} if k is None else {"K": k}), **filled)
    except NRSfMError as exc:
        return {**row, "status": "not run", "why": str(exc), "seconds": time.perf_counter() - t0}
    chosen = rec.info.get("K") if k is None else k
    out = {**row, "status": "ok", "e3d": e3d(rec.points_3d, seq.points_3d), "seconds": rec.runtime_s,
           "chosen_K": chosen}
    if "agreement" in rec.info:  # the agreement rule's distances to its reference, by K
        out["agreement"] = {str(k): v for k, v in rec.info["agreement"].items()}
    return out


def summarise(rows: list[dict]) -> tuple[list[list], list[dict]]:
    """Per (sequence, method, missing): the default's e3D, the best fixed K's, their ratio, and ``chance``: the share
    of the fixed Ks within 10% of the best (how often a K drawn at random would be)."""
    groups: dict[tuple, dict] = {}
    for r in rows:
        g = groups.setdefault((r["sequence"], r["method"], r["missing"]), {"default": None, "fixed": {}})
        if r["K"] == "default":
            g["default"] = r
        elif r["status"] == "ok":
            g["fixed"][r["K"]] = r["e3d"]
    table, summary = [], []
    for (name, method, missing), g in groups.items():
        d, fixed = g["default"], g["fixed"]
        best = min(fixed, key=fixed.get) if fixed else None
        if d is None or d["status"] != "ok":
            why = "not run" if d is None else f"not run: {d['why']}"
            table.append([name, method, f"{100 * missing:.0f}%", why, "", "", "", ""])
            continue
        ratio = d["e3d"] / fixed[best] if best is not None else None
        table.append([name, method, f"{100 * missing:.0f}%", f"{d['e3d']:.4f}", str(d.get("chosen_K") or "–"),
                      f"{fixed[best]:.4f} (K = {best})" if best is not None else "–",
                      f"{ratio:.2f}" if ratio is not None else "–", f"{d['seconds']:.1f}"])
        summary.append({"sequence": name, "method": method, "missing": missing, "e3d_default": d["e3d"],
                        "chosen_K": d.get("chosen_K"), "best_K": best,
                        "e3d_best": fixed[best] if best is not None else None, "ratio": ratio,
                        "chance": (sum(e <= 1.1 * fixed[best] for e in fixed.values()) / len(fixed)
                                   if best is not None else None)})
    return table, summary


def main(argv: list[str] | None = None) -> int:
    from nrsfm.errors import NRSfMError
    from nrsfm.solvers import available_solvers
    from nrsfm.solvers.kselect import FILLS

    from benchmarks.classic import benchmark_sequences, job_identity
    from benchmarks.common import add_run_arguments, worker_count

    p = argparse.ArgumentParser(prog="python -m benchmarks.defaults", description=__doc__.split("\n\n")[0])
    p.add_argument("--set", choices=("validation", "test", "holdout", "cmu"), default="validation", dest="which",
                   help="the validation set (default), the held-out test set, the second held-out set (S9) or "
                        "the CMU files the defaults were tuned on")
    p.add_argument("--root", help="data folder holding h36m/ and nrsfm/ (default: $NRSFM_DATA)")
    p.add_argument("--jobs", type=worker_count, default=1, help="parallel cells (joblib)")
    p.add_argument("--methods", default=None, help="comma-separated solvers (default: all registered but rank3)")
    p.add_argument("--missing", default="0", help="comma-separated fractions of entries to mark missing")
    p.add_argument("--fill", choices=FILLS, default="auto",
                   help="how CSF2 and SPM complete missing points, at the default and every fixed K (module docstring)")
    p.add_argument("--k-max", type=int, default=12, help="largest fixed K swept (default 12)")
    p.add_argument("--out", default=None, help="output folder (default: runs/defaults-SET)")
    add_run_arguments(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    try:
        methods = [m for m in available_solvers() if m != "rank3"] if args.methods is None else \
            [m.strip() for m in args.methods.split(",")]
        unknown = [m for m in methods if m not in available_solvers()]
        if unknown:
            raise ValueError(f"--methods: expected names among {available_solvers()}, got {', '.join(unknown)}")
        missing = parse_fractions(args.missing, "--missing")
        if args.which != "cmu":
            folder, jobs = validation_jobs(args.root, args.which)
        else:
            folder, jobs = benchmark_sequences(args.root, None, "defaults")
    except (NRSfMError, ValueError) as exc:
        print(f"defaults: error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    out = Path(args.out or f"runs/defaults-{args.which}")
    code = code_hash(__file__, Path(__file__).with_name("classic.py"))
    sizes = {j: load_job(j).points_2d.shape[:2] for j in jobs}
    cells = []
    for j in jobs:
        ident = job_identity(j) if Path(j).is_file() else {"job": j}
        label = job_label(j)
        for miss in missing:
            for m in methods:
                ks = [None] + (list(range(1, k_cap(*sizes[j], args.k_max) + 1)) if m in WITH_K else [])
                fill = args.fill if m in WITH_FILL and miss > 0 else "auto"  # complete tracks: nothing to fill
                tag = {} if fill == "auto" else {"fill": fill}
                for k in ks:
                    cells.append((f"{label}-{m}-K{k or 0}-m{miss:g}" + "".join(f"-{v}" for v in tag.values()),
                                  {**ident, "method": m, "K": k, "missing": miss, **tag, "code": code},
                                  (j, m, k, miss, fill)))
    done = run_cells_from_args(args, cells, run_cell, out, "defaults")
    if done is None:
        return 130
    rows, reused = done
    table, summary = summarise(rows)
    lines = []
    for m in methods:
        for miss in missing:
            s = [x for x in summary if x["method"] == m and x["missing"] == miss and x["ratio"] is not None]
            if s:
                within = sum(x["ratio"] <= 1.1 for x in s)
                lines.append(f"- {m}, {100 * miss:.0f}% missing: default within 10% of the best fixed K on {within} "
                             f"of {len(s)} sequences; worst ratio {max(x['ratio'] for x in s):.2f}, median "
                             f"{np.median([x['ratio'] for x in s]):.2f}; a K drawn at random: "
                             f"{sum(x['chance'] for x in s):.2f} expected")
    where = {"validation": "the validation set", "test": "the held-out test set",
             "holdout": "the second held-out set (S9)",
             "cmu": "the CMU files (the tuning set)"}[args.which] + \
        (f", {folder}" if folder is not None else ", synthetic stand-ins")
    text = (f"### Every solver at its defaults against its best fixed K ({where})\n\nCamera-frame e3D. "
            f"'best fixed K' is an oracle (chosen with the ground truth), over K = 1..{args.k_max} with "
            f"3K < min(2F, P)"
            + (f"; CSF2 and SPM complete missing points with fill = {args.fill} at every K" if args.fill != "auto"
               else "") + ".\n\n"
            + markdown_table(["sequence", "method", "missing", "e3D default", "K chosen", "best fixed K (oracle)",
                              "ratio", "time (s)"], table)
            + ("\n\n" + "\n".join(lines) if lines else "") + "\n")
    write_outputs(out, "defaults", text, rows, run_metadata(
        benchmark="solver defaults", set=args.which, data=str(folder or "synthetic stand-ins"), methods=methods,
        missing=missing, fill=args.fill, k_max=args.k_max, jobs=args.jobs, cells_reused=reused,
        wall_s=time.perf_counter() - t0), summary=summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
