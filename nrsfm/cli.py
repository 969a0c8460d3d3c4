"""The ``nrsfm`` command line.

    nrsfm info FILE [--json]
    nrsfm convert IN OUT.npz [--force]
    nrsfm solve FILE --method NAME [--set K=V ...] [--out OUT.npz] [--plot OUT.png] [--json] [--force]
                [--progress auto|always|never] [--jobs N] [--weak-perspective]
    nrsfm methods [NAME]
    nrsfm synth KIND OUT.npz [--frames F] [--points P] [--basis K] [--noise S] [--missing M] [--seed N]
    nrsfm demo [--out DIR] [--methods A,B] [--jobs N]

Bad input ends with one line on stderr and exit status 2 (no traceback).
Existing output files are never overwritten without ``--force``.

Threads: ``--threads N`` (default 1) caps the BLAS and OpenMP pools (threadpoolctl) and torch's
intra-op threads. The solvers' work is many small matrix products and decompositions, which gain little from a
second thread on an idle machine and lose several-fold when another process holds a core (threads that
spin-wait on the busy core); ``--threads 0`` leaves the libraries' own defaults.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

EXIT_BAD_INPUT = 2
#: ``nrsfm demo``'s default number of processes at most: each holds its own torch and BLAS (up to about 1 GB on
#: the demo's data), and beyond four the longest cells (EM-PND and the consensus on the face) set the wall time.
DEMO_MAX_JOBS = 4


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        raise _UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


class _UsageError(Exception):
    pass


def _build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="nrsfm", description="Non-rigid structure from motion toolbox.")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")
    p.add_argument("--threads", type=int, default=1,
                   help="BLAS and torch threads (default 1: never stalls on a busy core; 0: the libraries' "
                        "defaults)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    s = sub.add_parser("info", help="summarise and validate a sequence file (.npz or .mat), or a "
                                     "reconstruction written by 'nrsfm solve --out'")
    s.add_argument("file")
    s.add_argument("--json", action="store_true", help="print one JSON object")

    s = sub.add_parser("convert", help="convert a CMU .mat (Akhter or PND layout) to an nrsfm .npz")
    s.add_argument("input")
    s.add_argument("output")
    s.add_argument("--force", action="store_true", help="overwrite an existing output file")

    s = sub.add_parser("solve", help="reconstruct 3D from a sequence file")
    s.add_argument("file")
    s.add_argument("--method", "-m", default="rank3", help="solver name (see 'nrsfm methods')")
    s.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a solver parameter")
    s.add_argument("--out", help="write the reconstruction to this .npz")
    s.add_argument("--plot", help="write a PNG of input, reconstruction and ground truth")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--force", action="store_true", help="overwrite existing output files")
    s.add_argument("--progress", choices=["auto", "always", "never"], default="auto",
                   help="progress bars of the solver's iterations on stderr (auto: when stderr is a terminal)")
    s.add_argument("--jobs", type=int, default=1,
                   help="processes for the automatic K's solves (CSF2 and SPM with K = 0; default 1), each with "
                        "--threads threads")
    s.add_argument("--weak-perspective", action="store_true",
                   help="perspective tracks: normalise the pixels by the intrinsics and solve them as weak "
                        "perspective (Sequence.to_weak_perspective); metrics against the ground truth divided "
                        "by each frame's mean depth")

    s = sub.add_parser("methods", help="list the registered solvers, or one solver's parameters")
    s.add_argument("name", nargs="?", help="a solver: list its parameters (for --set) with their defaults")

    s = sub.add_parser("synth", help="write a synthetic sequence (.npz)")
    s.add_argument("kind", choices=["rigid", "lowrank", "human", "face", "surface"])
    s.add_argument("output")
    s.add_argument("--frames", type=int, default=None)
    s.add_argument("--points", type=int, default=30, help="points (rigid/lowrank)")
    s.add_argument("--basis", type=int, default=3, help="shape basis size (lowrank)")
    s.add_argument("--noise", type=float, default=0.0)
    s.add_argument("--missing", type=float, default=0.0)
    s.add_argument("--projection", choices=["orthographic", "perspective"], default="orthographic")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--force", action="store_true")

    s = sub.add_parser("demo", help="run every solver on the embedded synthetic data and write plots")
    s.add_argument("--out", default=None, help="output folder (default: a new nrsfm-demo-<time> folder)")
    s.add_argument("--methods", default=None, help="comma-separated solvers (default: all registered)")
    s.add_argument("--jobs", type=int, default=None,
                   help="processes solving the sequence x solver cells side by side, each with --threads threads "
                        f"(default: the CPU cores, at most {DEMO_MAX_JOBS})")
    return p


def main(argv: list[str] | None = None) -> int:
    from nrsfm.errors import NRSfMError

    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, stream=sys.stderr,
                            format="%(levelname)s %(name)s: %(message)s")
        if args.threads < 0:
            raise _UsageError(f"nrsfm: --threads: expected 0 (the libraries' defaults) or a count >= 1, got "
                              f"{args.threads} (see 'nrsfm --help')")
        torch_too = args.command in ("solve", "demo")
        with _thread_limits(args.threads, torch_too=torch_too, owns_process=argv is None):
            return _COMMANDS[args.command](args)
    except _UsageError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_BAD_INPUT
    except (NRSfMError, ValueError, FileNotFoundError, FileExistsError, IsADirectoryError, PermissionError) as exc:
        msg = str(exc).replace("\n", " ")
        print(f"nrsfm: error: {msg}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("nrsfm: interrupted", file=sys.stderr)
        return 130


@contextlib.contextmanager
def _thread_limits(threads: int, torch_too: bool, owns_process: bool):
    """Cap the BLAS pools at ``threads`` (0: no cap) for the duration of a command. Where the command owns its
    process (the ``nrsfm`` executable, not ``main([...])`` called from Python), also the OpenMP pools and, for
    the commands that may run torch, torch's intra-op threads, for the rest of the process: changing torch's
    count after its thread pool has run can hang it (pytorch#141358), so an embedding process keeps its own."""
    if threads == 0:
        yield
        return
    from threadpoolctl import threadpool_limits

    if torch_too and owns_process:
        import torch

        torch.set_num_threads(threads)
    with threadpool_limits(limits=threads, user_api=None if owns_process else "blas"):  # None: BLAS and OpenMP
        yield


# --------------------------------------------------------------------------- commands
def _is_reconstruction(path: str) -> bool:
    """Whether ``path`` is an .npz written by ``nrsfm solve --out`` (only its member names are read)."""
    import zipfile

    from nrsfm.io import is_reconstruction

    p = Path(path)
    if p.suffix.lower() != ".npz" or not p.is_file() or not zipfile.is_zipfile(p):
        return False
    with zipfile.ZipFile(p) as z:
        return is_reconstruction({n.removesuffix(".npy") for n in z.namelist()})


def _reconstruction_info(args: argparse.Namespace) -> int:
    from nrsfm.reconstruction import Reconstruction

    rec = Reconstruction.load(args.file)
    n_frames, n_points, _ = rec.points_3d.shape
    info = {"file": str(args.file), "kind": "reconstruction", "method": rec.method, "frames": n_frames,
            "points": n_points, "rotations": rec.rotations is not None, "iterations": rec.iterations,
            "converged": rec.converged, "runtime_s": rec.runtime_s, "params": rec.params}
    if args.json:
        print(json.dumps(info, default=str))
        return 0
    print(f"{args.file}: nrsfm reconstruction by '{rec.method}' (nrsfm.Reconstruction.load reads it)")
    print(f"  frames: {n_frames}")
    print(f"  points: {n_points}")
    print(f"  camera rotations: {'present' if rec.rotations is not None else 'absent'}")
    print(f"  iterations: {rec.iterations} ({'converged' if rec.converged else 'not converged'})")
    print(f"  run time: {rec.runtime_s:.3f} s")
    if rec.params:
        print(f"  parameters: {', '.join(f'{k}={v}' for k, v in rec.params.items())}")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from nrsfm.datasets import load_sequence

    if _is_reconstruction(args.file):
        return _reconstruction_info(args)
    seq = load_sequence(args.file)
    info = seq.summary()
    info["file"] = str(args.file)
    info["kind"] = "sequence"
    info["valid"] = True
    if args.json:
        print(json.dumps(info))
    else:
        print(f"{args.file}: valid nrsfm sequence '{seq.name}'")
        print(f"  frames: {seq.n_frames}")
        print(f"  points: {seq.n_points}")
        print(f"  projection: {seq.projection}")
        print(f"  ground truth: {'present' if seq.has_ground_truth else 'absent'}")
        print(f"  camera rotations: {'present' if seq.camera_rotations is not None else 'absent'}")
        print(f"  missing entries: {seq.missing_fraction:.2%}")
        if seq.edges is not None:
            print(f"  skeleton edges: {seq.edges.shape[0]}")
        for k, v in seq.meta.items():
            print(f"  {k}: {v}")
    return 0


def _cmd_convert(args: argparse.Namespace) -> int:
    from nrsfm.datasets import load_sequence

    out = Path(args.output)
    if out.suffix != ".npz":
        raise ValueError(f"output: expected a file name ending in .npz, got {args.output!r}")
    _check_outputs([args.output], args.force, inputs=(args.input,))
    seq = load_sequence(args.input)
    seq.save(out, overwrite=args.force)
    print(f"wrote {out}: {seq.n_frames} frames, {seq.n_points} points, ground truth "
          f"{'present' if seq.has_ground_truth else 'absent'}")
    return 0


def _check_outputs(paths: list[str | None], force: bool, inputs: tuple[str, ...] = ()) -> None:
    """Refuse outputs that exist (unless ``force``) and, even with ``force``, an output that is an input."""
    for p in paths:
        if p is None:
            continue
        if any(Path(p).resolve() == Path(i).resolve() for i in inputs):
            raise FileExistsError(f"{p}: this is the input file; choose another output name (--force does not "
                                  "replace an input)")
        if Path(p).exists() and not force:
            raise FileExistsError(f"{p}: the file exists; pass --force to replace it")


def _cmd_solve(args: argparse.Namespace) -> int:
    from nrsfm.datasets import load_sequence
    from nrsfm.metrics import classic_metrics
    from nrsfm.solvers import get_solver, params_from_strings

    spec = get_solver(args.method)
    params = params_from_strings(spec.params, args.set)
    if args.out is not None and not args.out.endswith(".npz"):
        raise ValueError(f"--out: expected a file name ending in .npz, got {args.out!r}")
    if args.plot is not None and not args.plot.lower().endswith(".png"):
        raise ValueError(f"--plot: expected a file name ending in .png, got {args.plot!r}")
    _check_outputs([args.out, args.plot], args.force, inputs=(args.file,))
    seq = load_sequence(args.file)
    if args.weak_perspective:
        seq = seq.to_weak_perspective()
    if args.jobs < 1:
        raise ValueError(f"--jobs: expected a number of processes >= 1, got {args.jobs}")
    show = args.progress == "always" or (args.progress == "auto" and sys.stderr.isatty())
    from joblib import parallel_config

    with contextlib.ExitStack() as stack:
        if args.jobs > 1:  # joblib's default for the solver's own Parallel calls (nrsfm.solvers.kselect)
            stack.enter_context(parallel_config(backend="loky", n_jobs=args.jobs,
                                                inner_max_num_threads=args.threads or None))
        if show:
            from nrsfm.progress import ProgressBars, listen

            bars = stack.enter_context(ProgressBars(sys.stderr))
            stack.enter_context(listen(bars))
        rec = spec.solve(seq, params)
    metrics: dict[str, float] = {}
    if seq.points_3d is not None:
        metrics = classic_metrics(rec.points_3d, seq.points_3d, pred_rotations=rec.rotations,
                                  gt_rotations=seq.camera_rotations)
    if args.out:
        rec.save(args.out, overwrite=args.force)
    if args.plot:
        from nrsfm.plotting import plot_reconstruction

        plot_reconstruction(seq, rec.points_3d, args.plot, title=f"{seq.name}: {spec.name}", overwrite=args.force)
    result: dict[str, Any] = {
        "method": spec.name, "sequence": seq.name, "file": str(args.file), "frames": seq.n_frames,
        "points": seq.n_points, "runtime_s": rec.runtime_s, "iterations": rec.iterations,
        "converged": rec.converged, "params": rec.params, "metrics": metrics,
        "out": args.out, "plot": args.plot,
    }
    if args.json:
        print(json.dumps(result, default=str))
    else:
        print(f"{seq.name}: {spec.name} on {seq.n_frames} frames x {seq.n_points} points in {rec.runtime_s:.3f} s "
              f"({rec.iterations} iterations, {'converged' if rec.converged else 'NOT converged'})")
        if rec.params.get("K") == 0 and "K" in rec.info:
            rule = rec.info.get("k_rule")
            print(f"  K (automatic):        {rec.info['K']}" + (f" ({rule} rule)" if rule else ""))
            flips = rec.info.get("depth_flips") or {}
            if flips:
                from nrsfm.solvers.kselect import steady_ks

                steady = steady_ks(flips)
                passed = [f"{k} ({100 * f:.1f}%)" for k, f in flips.items() if k not in steady]
                if passed:
                    print(f"  Ks passed over:       {', '.join(passed)}: depth reverses between frames more often "
                          f"than the steadiest K's ({100 * min(flips.values()):.1f}% of frame pairs)")
        if metrics:
            print(f"  e3D (camera frame):   {metrics['e3d']:.6g}")
            if "e3d_object" in metrics:
                print(f"  e3D (object frame):   {metrics['e3d_object']:.6g}")
                print(f"  camera error:         {metrics['rotation_error']:.6g}")
            print(f"  normalised error:     {metrics['normalized_error']:.6g}")
            print(f"  MPJPE (data units):   {metrics['mpjpe']:.6g}")
        else:
            print("  no ground truth in the file: no metrics")
        for label, p in (("reconstruction", args.out), ("plot", args.plot)):
            if p:
                print(f"  {label}: {p}")
    return 0


def _cmd_methods(args: argparse.Namespace) -> int:
    import dataclasses
    import inspect
    import typing

    from nrsfm.solvers import available_solvers, get_solver

    for name in available_solvers() if args.name is None else [args.name]:
        spec = get_solver(name)  # an unknown name: a clear error listing the known ones
        flags = [f for f, on in (("missing points", spec.handles_missing),
                                 ("perspective", spec.handles_perspective)) if on]
        print(f"{name:10s} {spec.description}{' [handles ' + ', '.join(flags) + ']' if flags else ''}")
    if args.name is not None:
        hints = typing.get_type_hints(spec.params)
        print(f"\nparameters ({spec.params.__name__}; nrsfm solve FILE -m {spec.name} --set NAME=VALUE):")
        for f in dataclasses.fields(spec.params):
            kind = getattr(hints[f.name], "__name__", str(hints[f.name]))
            print(f"  {f.name} ({kind}) = {f.default!r}")
        doc = inspect.cleandoc(spec.params.__doc__ or "")
        if "Attributes:" in doc:
            print("\n" + doc[doc.index("Attributes:"):])
    return 0


def _or(value: int | None, default: int) -> int:
    return default if value is None else value


def _cmd_synth(args: argparse.Namespace) -> int:
    from nrsfm.datasets import synthetic

    _check_outputs([args.output], args.force)
    if args.kind in ("rigid", "lowrank"):
        seq = synthetic.lowrank_sequence(_or(args.frames, 100), args.points, 1 if args.kind == "rigid" else args.basis,
                                         noise=args.noise, missing=args.missing, seed=args.seed)
    elif args.kind == "human":
        seq = synthetic.human_sequences(("S1",), ("walking",), (1,), n_frames=_or(args.frames, 200), noise=args.noise,
                                        missing=args.missing, projection=args.projection, seed=args.seed)[0]
    elif args.kind == "face":
        seq = synthetic.face_sequences(1, _or(args.frames, 300), noise=args.noise, missing=args.missing,
                                       seed=args.seed)[0]
    else:
        seq = synthetic.surface_sequence(_or(args.frames, 120), noise=args.noise, seed=args.seed)
    seq.save(args.output, overwrite=args.force)
    print(f"wrote {args.output}: {seq.name}, {seq.n_frames} frames, {seq.n_points} points")
    return 0


def _demo_cell(seq, name: str, out: Path, known: dict[str, Any] | None = None) -> dict[str, Any]:
    """One cell of ``nrsfm demo``: ``name`` on ``seq``, its metrics and plot (``{"error": message}`` where the
    solver declined the sequence). ``known``: reconstructions of ``seq`` by other solvers at their defaults, by
    name, that ``name`` may reuse (:func:`nrsfm.solvers.starts.remember_solution`). Runs in a worker process where
    ``--jobs`` > 1."""
    from nrsfm.errors import SolverError
    from nrsfm.metrics import classic_metrics, e3d_per_frame
    from nrsfm.plotting import plot_reconstruction
    from nrsfm.solvers import get_solver
    from nrsfm.solvers.starts import remember_solution

    for solver, rec in (known or {}).items():
        remember_solution(seq, solver, rec)
    spec = get_solver(name)
    try:
        rec = spec.solve(seq, spec.params())
    except SolverError as exc:
        return {"error": str(exc)}
    m = classic_metrics(rec.points_3d, seq.points_3d)
    stem = f"{seq.name.replace('/', '_')}_{name}"
    plot_reconstruction(seq, rec.points_3d, out / f"{stem}.png", title=f"{seq.name}: {name}")
    return {"e3d": m["e3d"], "ne": m["normalized_error"], "runtime": rec.runtime_s, "rec": rec,
            "curve": e3d_per_frame(rec.points_3d, seq.points_3d)}


def _cmd_demo(args: argparse.Namespace) -> int:
    """Every registered solver on the embedded synthetic sequences; a Markdown table and plots.

    The cells run in ``--jobs`` processes (one BLAS/torch pool of ``--threads`` each); the table keeps their
    order. The solvers whose reconstructions others reuse run first, on every sequence: EM-PND (CSF2 and SPM
    choose their K by agreement with it) and the consensus's components (EM-PND and PR); the workers of the
    other cells are handed their reconstructions instead of solving them again."""
    from joblib import Parallel, delayed

    from nrsfm.datasets import synthetic
    from nrsfm.plotting import plot_error_curve
    from nrsfm.solvers import available_solvers, get_solver
    from nrsfm.solvers.consensus import ConsensusParams
    from nrsfm.solvers.kselect import REFERENCE_SOLVER

    names = available_solvers() if args.methods is None else [m.strip() for m in args.methods.split(",")]
    for name in names:
        get_solver(name)  # unknown names fail before any work
    jobs = args.jobs if args.jobs is not None else min(DEMO_MAX_JOBS, os.cpu_count() or 1)
    if jobs < 1:
        raise ValueError(f"--jobs: expected a number of processes >= 1, got {jobs}")
    out = Path(args.out or time.strftime("nrsfm-demo-%Y%m%d-%H%M%S"))
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out}: the folder exists and is not empty; choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    sequences = [
        synthetic.lowrank_sequence(200, 30, 1, seed=0, name="rigid"),
        synthetic.lowrank_sequence(200, 30, 3, seed=0, name="lowrank-K3"),
        synthetic.human_sequences(("S9",), ("walking",), (1,), n_frames=200)[0],
        synthetic.face_sequences(1, 200)[0],
    ]
    for seq in sequences:
        seq.save(out / f"{seq.name.replace('/', '_')}.npz")
    print(f"nrsfm demo: {len(sequences)} synthetic sequences x {len(names)} solvers -> {out}/ ({jobs} "
          f"process{'es' if jobs > 1 else ''})")
    print()

    def run(cells):
        return Parallel(n_jobs=max(1, min(jobs, len(cells))), backend="loky", return_as="generator",
                        inner_max_num_threads=args.threads or None)(delayed(_demo_cell)(*c) for c in cells)

    shared = {REFERENCE_SOLVER, *ConsensusParams().parsed()[0]}
    first = [name for name in names if name in shared] if len(names) > 1 else []
    done: dict[tuple[str, str], dict[str, Any]] = {}
    if first:
        print(f"{', '.join(first)} first, on every sequence (csf2 and spm choose K by agreement with empnd; the "
              "consensus averages empnd and pr) ...", flush=True)
        cells = [(seq, name) for seq in sequences for name in first]
        done.update(zip([(s.name, n) for s, n in cells], run([(s, n, out) for s, n in cells])))
    print("| sequence | frames x points | method | e3D | normalised error | time (s) |")
    print("|---|---|---|---|---|---|")
    cells = [(seq, name) for seq in sequences for name in names]
    known = {seq.name: {n: done[seq.name, n]["rec"] for n in first if "rec" in done[seq.name, n]} for seq in sequences}
    rest = iter(run([(seq, name, out, known[seq.name]) for seq, name in cells if name not in first]))
    curves: dict[str, dict[str, Any]] = {}
    reused: set[str] = set()
    for seq, name in cells:
        cell = done[seq.name, name] if name in first else next(rest)
        if "error" in cell:
            print(f"| {seq.name} | {seq.n_frames} x {seq.n_points} | {name} | not run: {cell['error']} | | |",
                  flush=True)
        else:
            curves.setdefault(seq.name, {})[name] = cell["curve"]
            if cell["rec"].info.get("reused"):
                reused.add(f"{name} ({', '.join(cell['rec'].info['reused'])})")
            print(f"| {seq.name} | {seq.n_frames} x {seq.n_points} | {name} | {cell['e3d']:.4g} | {cell['ne']:.4g} | "
                  f"{cell['runtime']:.3f} |", flush=True)
        if name == names[-1] and curves.get(seq.name):
            plot_error_curve(curves[seq.name], out / f"{seq.name.replace('/', '_')}_e3d.png", ylabel="e3D per frame",
                             title=seq.name)
    print()
    if reused:
        print(f"{'; '.join(sorted(reused))}: reused those cells' reconstructions; their time is not counted again")
    print(f"plots and the input sequences are in {out}/ (try: nrsfm solve {out}/rigid.npz --method rank3)")
    return 0


_COMMANDS = {"info": _cmd_info, "convert": _cmd_convert, "solve": _cmd_solve, "methods": _cmd_methods,
             "synth": _cmd_synth, "demo": _cmd_demo}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
