"""Pseudo-3D labels: a classical NRSfM solver run on the training data, cut into per-sequence NRSfM inputs.

    python -m baselines.labels [--data synthetic|h36m] [--root DIR] --method csf2 [--set K=5] [--jobs 2]
                               [--backend loky|dask] [--scheduler ADDRESS] [--out DIR] [--rerun] [--no-progress]

The "+NN" baselines of the PRN paper (Table 1: CSF2 + NN, SPM + NN; Table 3: PR + NN) train a network on the 3D
shapes that a classical solver reconstructs from the training 2D, "applied to each sequence with the same strides
and camera settings as done in training PRN" (Sec. 4.1). PRN's training groups take frames ``gap`` (5) apart at
10 fps with the camera cycling 1, 2, 3, 4, 1, ... (one fixed camera per sequence is close to degenerate for
NRSfM). So every recording (subject, action, take) seen by C cameras is cut into ``gap * C`` NRSfM sequences
(:func:`multiview_cuts`): sequence ``(o, c)`` takes frames ``o, o + gap, o + 2 gap, ...`` and at its k-th frame
camera ``(k + c) mod C``. Together they hold every (frame, camera) pair of the recording exactly once, so every
training sample gets a label.

Each cut is solved by a registered :mod:`nrsfm` solver, in parallel (joblib: local processes with one BLAS thread
each, or a Dask cluster), and its reconstruction saved at once under a key made of the dataset, the cut, the
solver, its parameters and the code (:func:`code_version`): a rerun is instant and an interrupted run resumes.
A solver that fails on a cut, or returns shapes that are not finite or whose depth spread exceeds
``DIVERGED_DEPTH`` times the 2D spread, is recorded as failed; those frames get no label and are left out of
training (counted in the summary), never replaced. A point visible in no frame of a cut (the Stacked Hourglass
detections have no Neck/Nose) constrains nothing: the cut is solved without it and its label is NaN, so a network
learns that point from nothing but its own loss (PRN-L's PR term; none for a "+NN" row).

Solver settings: each solver's defaults, except for a cost bound (:data:`LABEL_DEFAULTS`; ``--set`` overrides
them). CSF2 and SPM choose K by their one-solve rules (rank and energy): their default agreement rule
(:mod:`nrsfm.solvers.kselect`) solves every K and EM-PND besides, five or six solves per 17-joint cut in place of
one. PR stops after 200 L-BFGS iterations (its default 2,000 runs about 1,500 on a 65-frame, 17-joint cut, 7 s):
the bound that keeps Human3.6M's 2,920 training cuts within about 30 minutes on 2 cores, as CSF2's.

Depth reflection. Orthographic NRSfM recovers each cut up to a global reflection ``z -> -z``, and labels of
mixed handedness would teach a network to flatten the depth. A mirror image negates the signed volume of every
four points; each cut is summarised by the mean signed volumes of the 4-point tuples whose volume keeps its sign
within cuts (the torso's, on human motion), and the cuts are mirrored so that these signatures agree
(:func:`resolve_reflections`: the signs of the leading eigenvector of their Gram matrix). No ground truth is used;
the label set keeps one handedness, and the single global ambiguity left is the one every orthographic method
has.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nrsfm.errors import NRSfMError, ValidationError
from nrsfm.io import atomic_write, read_npz
from nrsfm.sequence import Sequence

log = logging.getLogger(__name__)

#: A reconstruction whose depth spread is more than this many times its 2D spread has diverged.
DIVERGED_DEPTH = 20.0
BACKENDS = ("loky", "dask")


@dataclass(frozen=True)
class Cut:
    """One NRSfM input cut from multi-camera recordings.

    Attributes:
        key: ``subject/action/o<offset>c<camera phase>``, unique within a dataset.
        sequence: the `(F, P, 2)` tracks (no ground truth: the solver sees 2D only).
        sources: `(F, 2)` for each frame the index of the source sequence and its frame.
    """

    key: str
    sequence: Sequence
    sources: np.ndarray


@dataclass
class LabelSet:
    """Pseudo-labels for a list of training sequences.

    Attributes:
        labels: per training sequence `(F, P, 3)` camera-frame shapes in the units of its 2D; NaN where the cut
            holding that frame failed, and at the points that cut never saw.
        summary: solver, cuts, failed cuts, labelled frames, wall time, the labels' MPJPE against the ground truth
            (PRN protocol) where the sequences have it.
        failed: ``{cut key: reason}``.
    """

    labels: list[np.ndarray]
    summary: dict[str, Any]
    failed: dict[str, str] = field(default_factory=dict)


def code_version() -> str:
    """12 hex digits of the ``nrsfm`` package's source and of this module: part of every label's cache key."""
    import nrsfm

    digest = hashlib.sha1()
    for f in sorted(Path(nrsfm.__file__).resolve().parent.rglob("*.py")) + [Path(__file__).resolve()]:
        digest.update(f.name.encode())
        digest.update(f.read_bytes())
    return digest.hexdigest()[:12]


def multiview_cuts(sequences: list[Sequence], gap: int = 5) -> list[Cut]:
    """Cut per-camera recordings into NRSfM sequences with the camera alternation of PRN's training groups.

    Args:
        sequences: per-camera sequences with ``meta`` ``subject``, ``subaction`` (or ``action``) and ``camera``;
            the cameras of one recording must have the same frames (trailing frames of a longer one are cut).
        gap: frames between consecutive frames of a cut.

    Returns:
        ``gap * C`` cuts per recording seen by C cameras (fewer where a recording is shorter than ``gap``).
    """
    if gap < 1:
        raise ValidationError(f"gap: expected an integer >= 1, got {gap}")
    groups: dict[tuple[str, str], dict[str, int]] = {}
    for i, seq in enumerate(sequences):
        meta = seq.meta
        rec = (str(meta.get("subject", "")), str(meta.get("subaction", meta.get("action", seq.name))))
        cams = groups.setdefault(rec, {})
        cam = str(meta.get("camera", i))
        if cam in cams:
            raise ValidationError(f"{seq.name}: two sequences of recording {rec} claim camera {cam}; expected one "
                                  "per camera (meta 'camera')")
        cams[cam] = i
    cuts = []
    for (subject, take), cams in sorted(groups.items()):
        index = [cams[c] for c in sorted(cams)]  # camera order
        n_cams = len(index)
        n_frames = min(sequences[i].n_frames for i in index)
        for offset in range(min(gap, n_frames)):
            frames = np.arange(offset, n_frames, gap)
            for phase in range(n_cams):
                which = [index[(k + phase) % n_cams] for k in range(len(frames))]
                p2 = np.stack([sequences[i].points_2d[t] for i, t in zip(which, frames)])  # (F, P, 2)
                vis = None
                if any(sequences[i].visibility is not None for i in index):
                    vis = np.stack([sequences[i].weights[t] for i, t in zip(which, frames)])
                key = f"{subject}/{take}/o{offset}c{phase}"
                cuts.append(Cut(key, Sequence(points_2d=p2, visibility=vis, name=key),
                                np.stack([np.array(which), frames], axis=1)))
    return cuts


def _solve_cut(points_2d: np.ndarray, visibility: np.ndarray | None, name: str, method: str, params: dict,
               path: str) -> dict:
    """Worker: solve one cut and save its reconstruction (or the failure) to ``path`` atomically."""
    from threadpoolctl import threadpool_limits

    import nrsfm

    t0 = time.perf_counter()
    seen = np.ones(points_2d.shape[1], bool) if visibility is None else (np.asarray(visibility) > 0).any(axis=0)
    seq = Sequence(points_2d=points_2d, visibility=visibility, name=name).select_points(seen)
    status, message, shapes = "ok", "", np.full(points_2d.shape[:2] + (3,), np.nan)
    try:
        with threadpool_limits(limits=1):
            rec = nrsfm.solve(seq, method, **params)
        shapes[:, seen] = rec.points_3d
        spread_2d = float(np.nanmax(np.ptp(seq.points_2d, axis=1))) or 1.0
        spread_z = float(np.ptp(shapes[:, seen, 2], axis=1).max()) if np.isfinite(shapes[:, seen]).all() else np.inf
        if not np.isfinite(spread_z) or spread_z > DIVERGED_DEPTH * spread_2d:
            status, message = "failed", f"diverged: depth spread {spread_z:.3g} against 2D spread {spread_2d:.3g}"
            shapes = np.full_like(shapes, np.nan)
    except (NRSfMError, ValueError, np.linalg.LinAlgError, ArithmeticError) as exc:
        status, message = "failed", f"{type(exc).__name__}: {exc}"
    seconds = time.perf_counter() - t0
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out, overwrite=True) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, points_3d=shapes, status=np.array(status), message=np.array(message),
                                seconds=np.array(seconds))
    return {"status": status, "message": message, "seconds": seconds}


def _cache_folder(out_dir: Path, dataset: str, method: str, params: dict) -> Path:
    key = json.dumps({"method": method, "params": params, "code": code_version()}, sort_keys=True, default=str)
    return Path(out_dir) / dataset / f"{method}-{hashlib.sha1(key.encode()).hexdigest()[:12]}"


def _cut_path(folder: Path, cut: Cut) -> Path:
    digest = hashlib.sha1(cut.key.encode())
    digest.update(np.ascontiguousarray(cut.sequence.points_2d).tobytes())
    return folder / f"{cut.key.replace('/', '_').replace(' ', '-')}-{digest.hexdigest()[:10]}.npz"


def solve_cuts(cuts: list[Cut], method: str, params: dict | None = None, *, out_dir: str | os.PathLike,
               dataset: str, jobs: int = 1, backend: str = "loky", scheduler: str | None = None,
               progress: bool = True, rerun: bool = False) -> tuple[list[np.ndarray], dict[str, str], int]:
    """Solve every cut (those already saved for this dataset, solver, parameters and code are read back).

    Returns:
        The `(F, P, 3)` reconstruction of every cut (NaN for a failed one), ``{key: reason}`` of the failed ones,
        and how many were read back from the cache.
    """
    from joblib import Parallel, delayed, parallel_config
    from tqdm.auto import tqdm

    from nrsfm.solvers.registry import check_param_values, get_solver

    params = dict(params or {})
    check_param_values(get_solver(method).params, params, method)
    if backend not in BACKENDS:
        raise ValidationError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    folder = _cache_folder(Path(out_dir), dataset, method, params)
    paths = [_cut_path(folder, c) for c in cuts]
    todo = [i for i, p in enumerate(paths) if rerun or not p.exists()]
    reused = len(cuts) - len(todo)
    if reused:
        log.info("labels: %d of %d cuts read back from %s", reused, len(cuts), folder)
    if todo:
        calls = (delayed(_solve_cut)(cuts[i].sequence.points_2d, cuts[i].sequence.visibility, cuts[i].key, method,
                                     params, str(paths[i])) for i in todo)
        client = None
        if backend == "dask":
            from distributed import Client

            client = Client(scheduler) if scheduler else Client(processes=False)
        try:
            with parallel_config(backend=backend, n_jobs=jobs if backend == "loky" else -1):
                run = Parallel(return_as="generator_unordered")(calls)
                with tqdm(total=len(todo), desc=f"labels {method}", unit="cut", disable=not progress,
                          file=sys.stderr) as bar:
                    for _ in run:
                        bar.update()
        finally:
            if client is not None:
                client.close()
    shapes, failed = [], {}
    for cut, path in zip(cuts, paths):
        saved = read_npz(path, "a saved label")
        shapes.append(saved["points_3d"])
        if str(saved["status"]) != "ok":
            failed[cut.key] = str(saved["message"])
    return shapes, failed, reused


def signed_volumes(shapes: np.ndarray, tuples: np.ndarray) -> np.ndarray:
    """`(F, T)` signed volumes ``det[b - a, c - a, d - a]`` of the `(T, 4)` point ``tuples`` in every frame of
    `(F, P, 3)` shapes, each frame centred and scaled to unit norm. A mirror image negates every one."""
    x = shapes - shapes.mean(axis=1, keepdims=True)
    x = x / np.maximum(np.linalg.norm(x, axis=(1, 2), keepdims=True), 1e-300)
    a, b, c = (x[:, tuples[:, j]] - x[:, tuples[:, 0]] for j in (1, 2, 3))  # (F, T, 3) each
    # the triple product a . (b x c), written out: a batched LAPACK det is several times slower on 3 x 3
    return (a[..., 0] * (b[..., 1] * c[..., 2] - b[..., 2] * c[..., 1])
            - a[..., 1] * (b[..., 0] * c[..., 2] - b[..., 2] * c[..., 0])
            + a[..., 2] * (b[..., 0] * c[..., 1] - b[..., 1] * c[..., 0]))


def _tuples(n_points: int, max_tuples: int = 3000) -> np.ndarray:
    from itertools import combinations
    from math import comb

    if comb(n_points, 4) <= max_tuples:
        return np.array(list(combinations(range(n_points), 4)))
    rng = np.random.default_rng(0)
    return np.array([rng.choice(n_points, 4, replace=False) for _ in range(max_tuples)])


_MIRROR = np.array([1.0, 1.0, -1.0])


def resolve_reflections(reconstructions: list[np.ndarray], n_tuples: int = 40, iters: int = 200) -> np.ndarray:
    """Which of the `(F, P, 3)` camera-frame ``reconstructions`` to mirror (``z -> -z``) so that all share one
    handedness, without ground truth. NaN reconstructions (failed cuts) are never mirrored; the signatures use the
    points every solved cut has.

    A mirror image negates the signed volume of every four points (:func:`signed_volumes`), but most of them
    change sign with the pose too. So the ``n_tuples`` 4-point tuples whose volume keeps its sign best within the
    cuts (the mean over cuts of ``|mean| / std`` over a cut's frames, which a cut's own handedness does not
    affect) make each cut's signature, the mean of their volumes; and the signs ``s_c`` maximise the agreement
    ``sum_cd s_c s_d <v_c, v_d>`` of the unit signatures: the signs of the leading eigenvector of their Gram matrix
    (power iteration). Of the two global choices, the one that mirrors fewer cuts.

    Returns:
        `(len(reconstructions),)` booleans.
    """
    ok = [i for i, r in enumerate(reconstructions) if np.isfinite(r).any()]
    flips = np.zeros(len(reconstructions), bool)
    if len(ok) < 2:
        return flips
    points = np.logical_and.reduce([np.isfinite(reconstructions[i]).all(axis=(0, 2)) for i in ok])
    if points.sum() < 4:
        return flips
    tuples = _tuples(int(points.sum()))
    volumes = [signed_volumes(reconstructions[i][:, points], tuples) for i in ok]  # (F_c, T) each
    steadiness = np.mean([np.minimum(np.abs(v.mean(0)) / (v.std(0) + 1e-12), 10.0) for v in volumes], axis=0)
    chosen = np.argsort(-steadiness)[:n_tuples]
    sig = np.stack([v[:, chosen].mean(axis=0) for v in volumes])  # (n, n_tuples)
    sig /= np.maximum(np.linalg.norm(sig, axis=1, keepdims=True), 1e-300)
    u = sig @ sig.mean(axis=0)
    u = u / np.linalg.norm(u) if np.linalg.norm(u) > 0 else np.ones(len(ok)) / np.sqrt(len(ok))
    for _ in range(iters):
        new = sig @ (sig.T @ u)
        new /= max(float(np.linalg.norm(new)), 1e-300)
        done = np.allclose(new, u, atol=1e-12)
        u = new
        if done:
            break
    mirror = u < 0
    if mirror.sum() > len(ok) / 2:
        mirror = ~mirror
    flips[ok] = mirror
    return flips


#: The label pipeline's settings where they differ from a solver's defaults (the module docstring).
LABEL_DEFAULTS = {"csf2": {"k_rule": "rank"}, "spm": {"k_rule": "energy"}, "pr": {"max_iter": 200}}


def make_labels(sequences: list[Sequence], method: str, params: dict | None = None, *,
                out_dir: str | os.PathLike, dataset: str, gap: int = 5, jobs: int = 1, backend: str = "loky",
                scheduler: str | None = None, progress: bool = True, rerun: bool = False,
                truth: list[Sequence] | None = None) -> LabelSet:
    """Pseudo-labels for every frame of the orthographic training ``sequences``: cut (:func:`multiview_cuts`),
    solve (:func:`solve_cuts`), mirror to one handedness (:func:`resolve_reflections`), scatter back.

    ``dataset`` names the data in the cache key (use a different name for different data). ``truth``: sequences
    frame for frame with ``sequences`` whose ``points_3d`` score the labels (``label_mpjpe``, :func:`label_error`, in
    their units); default ``sequences`` themselves. Pass the original ones where ``sequences`` are weak-perspective
    conversions, whose ground truth is divided by each frame's depth.
    """
    if any(s.projection != "orthographic" for s in sequences):
        raise ValidationError("make_labels: expected orthographic tracks (the paper's +NN baselines use the "
                              "GT-ortho input); convert perspective tracks with seq.to_weak_perspective() first")
    t0 = time.perf_counter()
    params = {**LABEL_DEFAULTS.get(method, {}), **(params or {})}
    cuts = multiview_cuts(sequences, gap)
    shapes, failed, reused = solve_cuts(cuts, method, params, out_dir=out_dir, dataset=dataset, jobs=jobs,
                                        backend=backend, scheduler=scheduler, progress=progress, rerun=rerun)
    flips = resolve_reflections(shapes)
    labels = [np.full(s.points_2d.shape[:2] + (3,), np.nan) for s in sequences]
    for cut, rec, flip in zip(cuts, shapes, flips):
        rec = rec * _MIRROR if flip else rec
        for (i, t), shape in zip(cut.sources, rec):
            labels[i][t] = shape
    frames = int(sum(s.n_frames for s in sequences))
    labelled = int(sum(labelled_frames(lab).sum() for lab in labels))
    unlabelled_points = int(sum((~np.isfinite(lab[labelled_frames(lab)]).all(axis=2)).sum() for lab in labels))
    summary = {"method": method, "params": dict(params or {}), "dataset": dataset, "gap": gap, "cuts": len(cuts),
               "failed": len(failed), "reused": reused, "frames": frames, "labelled_frames": labelled,
               "unlabelled_points": unlabelled_points, "mirrored": int(flips.sum()),
               "seconds": time.perf_counter() - t0, "jobs": jobs, "backend": backend,
               "label_mpjpe": label_error(labels, sequences if truth is None else truth)}
    return LabelSet(labels, summary, failed)


def label_error(labels: list[np.ndarray], truth: list) -> float | None:
    """The PRN-protocol MPJPE of pseudo-labels as a network learns them (:func:`label_errors_per_frame`), in the
    ground truth's units (millimetres on Human3.6M, whatever the labels' own units); None without ground truth."""
    errors = []
    for lab, seq in zip(labels, truth):
        ok = labelled_frames(lab)
        if seq.points_3d is None or not ok.any():
            continue
        errors.append(label_errors_per_frame(lab[ok], seq.points_3d[ok]))
    return float(np.concatenate(errors).mean()) if errors else None


def label_errors_per_frame(labels: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """`(F,)` PRN-protocol MPJPE of `(F, P, 3)` pseudo-labels against `(F, P, 3)` ground truth as a network learns
    them: each labelled frame normalised by its own xy norm (:func:`baselines.supervised.normalised_targets`), then
    scaled by the ground truth's. Where some points have no label (NaN in some frame), the error is that of the
    points labelled in every frame, both sides restricted to them."""
    from baselines.supervised import normalised_targets
    from nrsfm.metrics import mpjpe_prn_per_frame
    from prn.data import denormalize

    points = np.isfinite(labels).all(axis=(0, 2))
    if not points.any():
        raise ValidationError("label_errors_per_frame: no point is labelled in every frame")
    labels, truth = labels[:, points], truth[:, points]
    return mpjpe_prn_per_frame(denormalize(normalised_targets([labels]), truth), truth)


def labelled_frames(labels: np.ndarray) -> np.ndarray:
    """`(F,)` whether each frame of `(F, P, 3)` labels has a label (some point finite: its cut was solved)."""
    return np.isfinite(labels).all(axis=2).any(axis=1)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m baselines.labels", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", choices=["synthetic", "h36m"], default=None,
                   help="default: h36m with --root, or when $NRSFM_DATA has h36m/; else the synthetic stand-in")
    p.add_argument("--root", help="data folder holding h36m/ (default: $NRSFM_DATA); implies --data h36m")
    p.add_argument("--method", "-m", default="csf2", help="registered solver (default csf2)")
    p.add_argument("--input", choices=["gt-ortho", "gt-persp", "sh"], default="gt-ortho",
                   help="Human3.6M's 2D: GT-ortho (default), GT-persp or the Stacked Hourglass detections (both as "
                        "weak-perspective tracks)")
    p.add_argument("--subjects", default=None, help="comma-separated training subjects (default: every one present)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a solver parameter")
    p.add_argument("--gap", type=int, default=5, help="frames between a cut's frames (default 5, as PRN)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    p.add_argument("--backend", choices=BACKENDS, default="loky")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (with --backend dask); default: a "
                                                     "local cluster in this process")
    p.add_argument("--out", default="runs/labels", help="label cache folder (default runs/labels)")
    p.add_argument("--rerun", action="store_true", help="solve every cut again")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    try:
        params = _params_from_strings(args.method, args.set)
        truth, dataset = _training_sequences(args)
        sequences = [s.to_weak_perspective() if s.projection == "perspective" else s for s in truth]
        result = make_labels(sequences, args.method, params, out_dir=args.out, dataset=dataset, gap=args.gap,
                             jobs=args.jobs, backend=args.backend, scheduler=args.scheduler,
                             progress=not args.no_progress, rerun=args.rerun, truth=truth)
    except (NRSfMError, FileNotFoundError, ValueError) as exc:
        print(f"labels: error: {exc}", file=sys.stderr)
        return 2
    s = result.summary
    if not s["labelled_frames"]:
        reasons = "; ".join(f"{k}: {v}" for k, v in list(result.failed.items())[:3])
        print(f"labels: error: every one of the {s['cuts']} cuts failed, no frame has a label ({reasons} ...)",
              file=sys.stderr)
        return 1
    print("| solver | data | cuts | failed | labelled frames | wall time (s) | label MPJPE (mm, PRN protocol) |")
    print("|---|---|---|---|---|---|---|")
    mp = f"{s['label_mpjpe']:.1f}" if s["label_mpjpe"] is not None else "no ground truth"
    print(f"| {s['method']} | {s['dataset']} | {s['cuts']} | {s['failed']} | {s['labelled_frames']} of "
          f"{s['frames']} | {s['seconds']:.1f} | {mp} |")
    if result.failed:
        print(f"\nfailed cuts (left out of training): " + "; ".join(f"{k}: {v}" for k, v in
                                                                   list(result.failed.items())[:10])
              + (" ..." if len(result.failed) > 10 else ""))
    return 0


def _training_sequences(args: argparse.Namespace) -> tuple[list[Sequence], str]:
    """The training sequences of the chosen data and input (perspective ones as loaded, with their ground truth in
    millimetres), and the dataset's cache name."""
    from nrsfm.datasets import find_dataset, h36m

    # an explicit --root means Human3.6M, as in the benchmark tables: a wrong folder is an error, not the stand-in
    root = find_dataset("h36m", args.root, required=args.data == "h36m" or (args.data is None and bool(args.root)))
    if args.data == "synthetic" or (args.data is None and root is None):
        from nrsfm.datasets.synthetic import human_sequences

        return (human_sequences(h36m.TRAIN_SUBJECTS, projection="orthographic", n_frames=200, takes=2),
                "synthetic-200-2-0-gt-ortho")
    subjects = [s for s in h36m.TRAIN_SUBJECTS if (root / s).is_dir()]
    if args.subjects:
        wanted = [s.strip() for s in args.subjects.split(",")]
        if not set(wanted) <= set(subjects):
            raise ValidationError(f"--subjects: expected training subjects among {subjects}, got {wanted}")
        subjects = wanted
    if not subjects:
        raise ValidationError(f"{root}: expected training subjects {h36m.TRAIN_SUBJECTS}, found none")
    stride = h36m.detect_stride(root, subjects[0])
    seqs = h36m.load_h36m(root, subjects, input=args.input, stride=stride, source_fps=50.0)
    # the dataset name is the one benchmarks.table1 gives these labels, so that both share the saved cuts
    return seqs, f"h36m-{stride}-{args.input}"


def _params_from_strings(method: str, assignments: list[str]) -> dict:
    """``--set NAME=VALUE`` strings as the solver's typed parameters (only those given)."""
    from nrsfm.solvers.registry import get_solver, params_from_strings

    params = params_from_strings(get_solver(method).params, assignments)
    return {a.split("=", 1)[0].strip(): getattr(params, a.split("=", 1)[0].strip()) for a in assignments}


if __name__ == "__main__":
    sys.exit(main())
