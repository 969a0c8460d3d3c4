"""CSF2's automatic K against every K: noise-free and noisy synthetic tracks, and the CMU files.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.auto_k [--root DIR] [--jobs N] [--sequences a,b] [--missing 0.2]
        [--out DIR] [--rerun] [--no-progress]

For each sequence, CSF2 (:mod:`nrsfm.solvers.csf2`, its defaults otherwise) runs with every K from 1 to the
cap (8, and 3K < min(2F, P)); the table gives the camera-frame e3D at the K of the automatic rule
(:func:`nrsfm.solvers.starts.auto_k`), at the K of a simpler rank rule (:func:`previous_rule`: one basis
shape more than ``ceil(r / 3)`` always, the cap on full-rank tracks), at the cap, and the best K (known only
with the ground truth). The sequences: synthetic K = 2-4 low-rank tracks (300 frames, 41 points) of a smoothly
turning camera, noise-free and with 1% and 5% 2D noise, three seeds; K = 3 and 5 with random cameras; the
synthetic faces; with data, every CMU file as it is and with 1% noise (the shark also with 0.3%). Writes
CSV/JSON/Markdown to ``runs/auto_k``; cells are saved and resumed as in ``benchmarks.classic``.

``--missing 0.2`` first marks that fraction of entries missing (:func:`nrsfm.datasets.synthetic.drop_entries`) and
runs CSF2-occlusion; the ranks are then the visible entries' exact rank
(:func:`nrsfm.lowrank.visible_rank`) and the noisy tracks' rank
(:func:`nrsfm.lowrank.noise_visible_rank`), and the simpler rule is the exact rank, else the cap. Every K runs
only where the two rules differ; elsewhere (and on the CMU files, where CSF2-occlusion takes tens of seconds a K)
only the rules' K and the cap, so "best K" is over those. Output to ``runs/auto_k-missing0.2``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from benchmarks.common import code_hash, markdown_table, run_cells_from_args, run_metadata, write_outputs

log = logging.getLogger("benchmarks.studies.auto_k")

SMOOTH = [(k, seed, noise) for k in (2, 3, 4) for noise in (0.0, 0.01, 0.05) for seed in (1, 2, 3)]
RANDOM = [(k, noise) for k in (3, 5) for noise in (0.0, 0.01)]
FACE_NOISE = (0.0, 0.005, 0.02)


def synthetic_jobs() -> list[str]:
    """The generated sequences, as jobs for :func:`make_sequence`."""
    return ([f"smooth:{k}:{seed}:{noise:g}" for k, seed, noise in SMOOTH] + [f"random:{k}:4:{noise:g}"
            for k, noise in RANDOM] + [f"face:{noise:g}" for noise in FACE_NOISE])


def file_job(job: str) -> tuple[str, str] | None:
    """``(path, noise)`` of a ``FILE:NOISE`` job, None for a generated sequence."""
    if job.split(":")[0] in ("smooth", "random", "face"):
        return None
    path, _, noise = job.rpartition(":")
    return path, noise


def make_sequence(job: str, missing: float = 0.0):
    """``smooth:K:SEED:NOISE`` / ``random:K:SEED:NOISE`` (300 x 41 low-rank tracks), ``face:NOISE`` (one 300-frame
    synthetic face) or ``FILE:NOISE`` (a CMU file, with 2D noise of that fraction of the tracks' RMS, fixed
    seed) as a :class:`~nrsfm.sequence.Sequence`, with ``missing`` of its entries hidden."""
    from nrsfm.datasets.synthetic import drop_entries

    return drop_entries(_make_complete(job), missing)


def _make_complete(job: str):
    from nrsfm.datasets.synthetic import face_sequences, lowrank_sequence

    kind, *rest = job.split(":")
    if kind in ("smooth", "random"):
        k, seed, noise = int(rest[0]), int(rest[1]), float(rest[2])
        return lowrank_sequence(300, 41, k, cameras=kind, seed=seed, noise=noise, name=job)
    if kind == "face":
        return face_sequences(1, 300, noise=float(rest[0]))[0].replace(name=job)
    import zlib

    import nrsfm

    path, noise_text = file_job(job)
    seq = nrsfm.load_sequence(path)
    noise = float(noise_text)
    if noise:
        p = seq.points_2d
        scale = np.sqrt(((p - p.mean(axis=1, keepdims=True)) ** 2).mean())
        rng = np.random.default_rng(zlib.crc32(f"auto-k-{seq.name}-{noise}".encode()))
        seq = seq.replace(points_2d=p + noise * scale * rng.standard_normal(p.shape))
    return seq.replace(name=f"{seq.name}" + (f"+{noise:g}" if noise else ""))


def previous_rule(w: np.ndarray, k_max: int = 8, rel_tol: float = 1e-6) -> int:
    """A simpler automatic K for comparison (complete tracks): ``min(cap, ceil(r / 3) + 1)``, r the numerical
    rank of the centred W (full on noisy tracks, so the cap there)."""
    cap = max(1, min(k_max, (min(w.shape) - 1) // 3))
    s = np.linalg.svd(w - w.mean(axis=1, keepdims=True), compute_uv=False)
    rank = int(np.count_nonzero(s > rel_tol * s[0])) if s[0] > 0 else 1
    return max(1, min(cap, -(-rank // 3) + 1))


def rank_info(job: str, missing: float = 0.0) -> dict:
    """The automatic rule's inputs and outputs on a job's W: numerical rank (with missing entries: the visible
    entries' exact rank), noise rank, K (new and old), cap."""
    from nrsfm.lowrank import noise_rank, noise_visible_rank, visible_rank
    from nrsfm.solvers.starts import auto_k, auto_k_max_rank, k_for_rank

    seq = make_sequence(job, missing)
    w = seq.measurement_matrix()
    cap = max(1, min(8, (min(w.shape) - 1) // 3))
    if missing > 0:  # auto_k's steps, one by one (each ladder of fits once)
        mask = np.repeat(seq.weights > 0, 2, axis=0)
        exact = visible_rank(w, mask, auto_k_max_rank(w))[0]
        noisy = 0 if exact else noise_visible_rank(w, mask, auto_k_max_rank(w))
        return {"numerical_rank": exact, "noise_rank": noisy, "auto_k": k_for_rank(exact or noisy, cap),
                "previous_k": k_for_rank(exact, cap), "cap": cap}
    s = np.linalg.svd(w - w.mean(axis=1, keepdims=True), compute_uv=False)
    return {"numerical_rank": int(np.count_nonzero(s > 1e-6 * s[0])), "noise_rank": noise_rank(s, w.shape),
            "auto_k": auto_k(w), "previous_k": previous_rule(w), "cap": cap}


def run_one(job: str, k: int, missing: float = 0.0) -> dict:
    """CSF2 with K = ``k`` on one sequence: its camera-frame e3D, time and shape start (errors recorded, never
    raised)."""
    import nrsfm
    from nrsfm.errors import NRSfMError
    from nrsfm.metrics import e3d

    seq = make_sequence(job, missing)
    t = time.perf_counter()
    try:
        rec = nrsfm.solve(seq, "csf2", K=k)
    except NRSfMError as exc:
        return {"sequence": seq.name, "K": k, "status": "error", "why": str(exc)}
    return {"sequence": seq.name, "K": k, "status": "ok", "e3d": e3d(rec.points_3d, seq.points_3d),
            "seconds": time.perf_counter() - t, "shape_start": rec.info["shape_start"]}


def _at(errors: dict[int, float], k: int) -> str:
    return f"{errors[k]:.4f} (K = {k})" if k in errors else f"not run (K = {k})"


def main(argv: list[str] | None = None) -> int:
    from benchmarks.classic import job_identity, parse_data_benchmark

    def options(p):
        p.add_argument("--missing", type=float, default=0.0, help="fraction of entries to mark missing (fixed seed)")

    def check(args):
        if not 0 <= args.missing < 1:
            raise ValueError(f"--missing: expected a fraction in [0, 1), got {args.missing}")

    parsed = parse_data_benchmark("auto_k", __doc__, argv, options=options, check=check,
                                  out_help="output folder (default: runs/auto_k, runs/auto_k-missingX)")
    if parsed is None:
        return 2
    args, folder, files, _ = parsed
    missing = args.missing
    t0 = time.perf_counter()
    out = Path(args.out or f"runs/auto_k{'-missing' + str(missing) if missing else ''}")
    jobs = synthetic_jobs()
    if folder is not None:
        jobs += [f"{f}:{noise:g}" for f in files for noise in (0.0, 0.01)]
        jobs += [f"{f}:0.003" for f in files if Path(f).stem.startswith("jaws")]
    from joblib import Parallel, delayed

    # the noisy ladder of noise_visible_rank takes seconds a sequence with missing entries: in parallel
    info = dict(zip(jobs, Parallel(n_jobs=args.jobs)(delayed(rank_info)(j, missing) for j in jobs)))
    code = code_hash(__file__, Path(__file__).parent.parent / "classic.py")

    def label_and_identity(job: str) -> tuple[str, dict]:  # the cells' file name; a file's path and bytes
        if file_job(job) is None:
            return job.replace(":", "-"), {"job": job}
        path, noise = file_job(job)
        return f"{Path(path).stem}-{noise}", {**job_identity(path), "noise": noise}

    named = {j: label_and_identity(j) for j in jobs}  # a file's bytes are hashed once

    def ks(j: str) -> list[int]:  # with missing entries every K only where the rule changed (module docstring)
        if missing and (file_job(j) is not None or info[j]["auto_k"] == info[j]["previous_k"]):
            return sorted({info[j]["auto_k"], info[j]["previous_k"], info[j]["cap"]})
        return list(range(1, info[j]["cap"] + 1))

    cells = [(f"{named[j][0]}-K{k}", {**named[j][1], "K": k, "missing": missing, "code": code}, (j, k, missing))
             for j in jobs for k in ks(j)]
    done = run_cells_from_args(args, cells, run_one, out, "auto_k")
    if done is None:
        return 130
    rows, reused = done
    by_job: dict[str, dict[int, float]] = {j: {} for j in jobs}
    names = {}
    for (_, _, (j, k, _)), r in zip(cells, rows):
        names[j] = r["sequence"]
        if r["status"] == "ok":
            by_job[j][k] = r["e3d"]
    table, summary = [], []
    for j in jobs:
        errors, i = by_job[j], info[j]
        best = min(errors, key=errors.get) if errors else None
        table.append([names[j], f"{i['numerical_rank']} / {i['noise_rank'] or '–'}", _at(errors, i["auto_k"]),
                      _at(errors, i["previous_k"]), _at(errors, i["cap"]),
                      _at(errors, best) if best is not None else "not run"])
        if best is not None and i["auto_k"] in errors and i["previous_k"] in errors:
            summary.append({"sequence": names[j], **i, "e3d_auto": errors[i["auto_k"]],
                            "e3d_previous": errors[i["previous_k"]], "e3d_cap": errors.get(i["cap"]),
                            "best_k": best, "e3d_best": errors[best]})
    md = markdown_table(["sequence", f"{'visible' if missing else 'numerical'} rank / noise rank", "automatic K",
                         "previous rule", "cap",
                         "best K (needs the ground truth)"], table)
    better = sum(s["e3d_auto"] < 0.99 * s["e3d_previous"] for s in summary)
    worse = sum(s["e3d_auto"] > 1.01 * s["e3d_previous"] for s in summary)
    at_best = sum(s["e3d_auto"] <= 1.1 * s["e3d_best"] for s in summary)
    where = f"{len(files)} CMU files and synthetic tracks" if folder is not None else "synthetic tracks, no CMU data"
    text = (f"### CSF2's automatic K ({where}, {100 * missing:.0f}% missing)\n\nCamera-frame e3D of CSF2 at each "
            f"rule's K (best K: over the K run). smooth:K:SEED:NOISE "
            f"and random:K:SEED:NOISE: 300 x 41 synthetic tracks of true K (cameras turning smoothly, or at random) "
            f"with that 2D noise; face:NOISE: a synthetic face; NAME+NOISE: a CMU file with 2D noise of that "
            f"fraction of its RMS. Numerical rank at 1e-6; noise rank: the threshold's, where the spectrum has a "
            f"gap.\n\n{md}\n\n"
            f"Automatic K against the previous rule: better (by more than 1%) on {better}, worse on {worse}, "
            f"the same on {len(summary) - better - worse} of {len(summary)} sequences; within 10% of the best K "
            f"on {at_best}.\n")
    write_outputs(out, "auto_k", text, rows, run_metadata(
        benchmark="csf2 automatic K", missing=missing, jobs=args.jobs, data=str(folder or "synthetic only"),
        cells_reused=reused, wall_s=time.perf_counter() - t0), summary=summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
