"""Helpers shared by the table scripts: run metadata, config hashes, atomic CSV/JSON, Markdown, and resumable
parallel runs of independent cells (:func:`run_cells`)."""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence


def config_hash(config: dict[str, Any]) -> str:
    """12 hex digits identifying a configuration (cache keys, output folders)."""
    return hashlib.sha1(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:12]


def code_hash(*extra: str | Path) -> str:
    """12 hex digits of the source of the ``nrsfm`` package and of the ``extra`` files: the part of a cache key
    that makes a saved result be reused only by the code that computed it (any edit, installed or not, changes
    it; a git hash would not see uncommitted edits or a pip-installed copy)."""
    import nrsfm

    digest = hashlib.sha1()
    files = sorted(Path(nrsfm.__file__).resolve().parent.rglob("*.py")) + [Path(f).resolve() for f in extra]
    for f in files:
        digest.update(f.name.encode())
        digest.update(f.read_bytes())
    return digest.hexdigest()[:12]


class Interrupted(Exception):
    """Raised by :func:`run_cells` on Ctrl-C; the message says what was saved and how to resume."""


def _indexed(i: int, fn: Callable[..., Any], args: tuple) -> tuple[int, Any]:
    return i, fn(*args)


def run_cells(cells: Sequence[tuple[str, dict[str, Any], tuple]], fn: Callable[..., Any], *, jobs: int,
              cache_dir: Path, rerun: bool = False, progress: bool = True, desc: str = "cells") -> tuple[list, int]:
    """``fn(*args)`` for every cell ``(label, key, args)``, in parallel over ``jobs`` processes (joblib), each
    result saved to ``cache_dir/<label>-<config_hash(key)>.json`` as soon as it arrives, so an interrupted run
    resumes: a later call with the same keys reuses the saved results (unless ``rerun``) and solves only the
    rest. ``key`` must name everything the result depends on (inputs, parameters, :func:`code_hash`).

    ``fn`` must return JSON-serialisable data (numpy scalars are converted). A tqdm bar on stderr counts the
    cells still to solve (``progress=False`` hides it). Returns the results in the order of ``cells`` and the
    number reused. Ctrl-C raises :class:`Interrupted` (the finished cells stay saved).
    """
    from joblib import Parallel, delayed
    from tqdm.auto import tqdm

    results: list[Any] = [None] * len(cells)
    paths = [cache_dir / f"{label}-{config_hash(key)}.json" for label, key, _ in cells]
    todo = []
    for i, path in enumerate(paths):
        if not rerun and path.exists():
            try:
                results[i] = json.loads(path.read_text())
                continue
            except (OSError, json.JSONDecodeError):  # a damaged file: solve the cell again
                pass
        todo.append(i)
    reused = len(cells) - len(todo)
    if reused:
        logging.getLogger(__name__).info("%s: reusing %d of %d cells saved by an earlier run in %s (--rerun solves "
                                         "them again)", desc, reused, len(cells), cache_dir)
    if todo:
        run = Parallel(n_jobs=jobs, return_as="generator_unordered")(
            delayed(_indexed)(i, fn, cells[i][2]) for i in todo)
        done = 0
        try:
            with tqdm(total=len(todo), desc=desc, unit="cell", disable=not progress, file=sys.stderr) as bar:
                for i, result in run:
                    text = json.dumps(result, indent=2, default=_plain)
                    write_text_atomic(paths[i], text)
                    results[i] = json.loads(text)  # the saved form, so a resumed run returns the same data
                    done += 1
                    bar.update()
        except KeyboardInterrupt:
            raise Interrupted(f"{desc}: interrupted after {done} of {len(todo)} cells; every finished cell is saved "
                              f"in {cache_dir}: run the same command again to resume") from None
    return results, reused


def worker_count(text: str) -> int:
    """joblib's ``n_jobs`` as a command-line value: N workers, or -1 for every core, -2 for all but one, ... (0
    means nothing)."""
    value = int(text)
    if value == 0:
        raise argparse.ArgumentTypeError("expected a number of workers >= 1, or -1 for every core; got 0")
    return value


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """``--rerun`` and ``--no-progress``: the options of :func:`run_cells_from_args`."""
    parser.add_argument("--rerun", action="store_true",
                        help="solve every cell again instead of reusing the results an earlier run saved under "
                             "OUT/cells (by default an interrupted run resumes where it stopped)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def parse_study_arguments(name: str, doc: str, argv: list[str] | None,
                          options: Callable[[argparse.ArgumentParser], None]) -> argparse.Namespace:
    """The command line of ``python -m benchmarks.studies.NAME`` over the validation set of ``benchmarks.defaults``:
    ``--root``, ``--jobs``, the study's ``options``, ``--out`` (default ``runs/NAME``) and
    :func:`add_run_arguments`; then INFO logging on stderr."""
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.studies.{name}", description=doc.split("\n\n")[0])
    p.add_argument("--root", help="data folder holding h36m/ and nrsfm/ (default: $NRSFM_DATA)")
    p.add_argument("--jobs", type=worker_count, default=1, help="parallel sequences (joblib)")
    options(p)
    p.add_argument("--out", default=f"runs/{name}", help=f"output folder (default: runs/{name})")
    add_run_arguments(p)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    return args


def parse_fractions(text: str, option: str) -> list[float]:
    """``"0,0.2"`` -> ``[0.0, 0.2]``: the comma-separated fractions in [0, 1) of option ``option`` (missing points,
    dropped entries); anything else raises :class:`nrsfm.errors.ValidationError` saying what was expected."""
    from nrsfm.errors import ValidationError

    try:
        out = [float(v) for v in text.split(",")]
    except ValueError:
        out = []
    if not out or not all(0 <= v < 1 for v in out):
        raise ValidationError(f"{option}: expected comma-separated fractions in [0, 1) such as 0,0.2, got {text!r}")
    return out


def run_cells_from_args(args: argparse.Namespace, cells: Sequence[tuple[str, dict[str, Any], tuple]],
                        fn: Callable[..., Any], out: Path, desc: str) -> tuple[list, int] | None:
    """:func:`run_cells` for a benchmark's command line (``args`` from :func:`add_run_arguments` plus ``--jobs``),
    saving under ``out/cells``. On Ctrl-C it prints what was saved and returns None (exit status 130)."""
    try:
        return run_cells(cells, fn, jobs=args.jobs, cache_dir=out / "cells", rerun=args.rerun,
                         progress=not args.no_progress, desc=desc)
    except Interrupted as exc:
        print(exc, file=sys.stderr)
        return None


def _plain(value: Any) -> Any:
    """JSON form of numpy scalars and arrays (``run_cells``)."""
    import numpy

    if isinstance(value, numpy.generic):
        return value.item()
    if isinstance(value, numpy.ndarray):
        return value.tolist()
    raise TypeError(f"run_cells: a result holds {type(value).__name__}, expected JSON data")


def git_hash() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, timeout=5, cwd=Path(__file__).resolve().parent).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "") if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


#: The commit a :func:`run_table` run started from: the code that runs, though the checkout may move on before
#: the run ends.
_started_from: str | None = None


def run_metadata(**extra: Any) -> dict[str, Any]:
    """Versions, git hash (the one a :func:`run_table` run started from), machine and time, plus ``extra``
    (parameters, seeds, data)."""
    import numpy
    import scipy

    meta: dict[str, Any] = {
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "git": _started_from or git_hash(), "python": platform.python_version(),
        "numpy": numpy.__version__, "scipy": scipy.__version__, "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }
    try:
        import torch

        meta["torch"] = torch.__version__
        meta["torch_threads"] = torch.get_num_threads()
        meta["cuda"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    except ImportError:  # pragma: no cover
        pass
    meta.update(extra)
    return meta


def write_text_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_json(path: Path, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, default=str))


def checkpoint_progress(run: Path) -> dict[str, Any]:
    """Where the trainings of a table run (its ``--out`` folder ``run``) got to, from their checkpoints
    ``cache/*/checkpoint.pt``: the iteration, the last two history entries and the monitor list (read on the CPU);
    ``checkpoint_error`` for a checkpoint being replaced at this moment (the next reading gets it)."""
    import torch

    entry: dict[str, Any] = {}
    for ckpt in Path(run).glob("cache/*/checkpoint.pt"):
        try:
            state = torch.load(ckpt, map_location="cpu", weights_only=False)
        except Exception as exc:  # noqa: BLE001 - any partial read; reported, read again later
            entry["checkpoint_error"] = repr(exc)
            continue
        entry.update(iteration=state["iteration"], history=state["history"][-2:], monitor=state.get("monitor", []))
    return entry


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    if not rows:
        write_text_atomic(path, "")
        return
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols)
    w.writeheader()
    w.writerows(rows)
    write_text_atomic(path, buf.getvalue())


def write_outputs(out: Path, name: str, text: str, rows: list[dict[str, Any]], meta: dict[str, Any],
                  **extra: Any) -> None:
    """A benchmark's results: ``text`` (Markdown) printed and written to ``out/NAME.md``, ``rows`` to
    ``out/NAME.csv``, and ``{"meta": meta, "rows": rows, **extra}`` to ``out/NAME.json``."""
    print(text)
    write_csv(out / f"{name}.csv", rows)
    write_json(out / f"{name}.json", {"meta": meta, "rows": rows, **extra})
    write_text_atomic(out / f"{name}.md", text)


def markdown_table(header: list[str], rows: list[list[Any]]) -> str:
    def fmt(v: Any) -> str:
        if v is None:
            return "–"
        if isinstance(v, float):
            return f"{v:.1f}" if abs(v) >= 1 else f"{v:.4f}"
        return str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def add_training_arguments(p: argparse.ArgumentParser) -> None:
    """The options every table that trains networks shares: seed, device, progress bars, cache reuse."""
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    p.add_argument("--no-progress", action="store_true", help="hide the training progress bars")
    p.add_argument("--resume", dest="retrain", action="store_false",
                   help="reuse cached models and resume interrupted training from its checkpoint (the default)")
    p.add_argument("--retrain", dest="retrain", action="store_true",
                   help="ignore cached models and checkpoints; train from scratch")
    p.set_defaults(retrain=False)
    p.add_argument("--labels-dir", default=None,
                   help="the pseudo-labels' cache (default: <out>/labels); tables run together can share one")
    p.add_argument("--compress-schedule", action="store_true",
                   help="scale the lr step (the paper's x0.8 every 5,000 iterations) by --iterations / 70,000, so "
                        "that a shorter run ends as far down the schedule as the paper's 70,000 (default: the "
                        "paper's step whatever the count; the table states which)")


def choose_data(args: argparse.Namespace, candidates: Sequence[tuple[str, tuple[str, ...]]],
                table: str) -> str | None:
    """Settle ``args.data`` and ``args.root`` for a table whose real data is one of ``candidates``, each (name,
    dataset folders), in order of priority; returns the stand-in notice to print first, or None on real data.

    ``--data`` as given (a real name without data then fails where it is loaded, saying where it looked);
    otherwise the first candidate whose folders all lie under ``--root`` or ``$NRSFM_DATA``, else the embedded
    synthetic stand-in. An explicit ``--root`` holding none of them is an error, not a silent stand-in.
    """
    from nrsfm.datasets import data_root, find_dataset
    from nrsfm.errors import ValidationError

    root = data_root(args.root)
    if args.data is None and root is not None:
        for name, folders in candidates:
            if all(find_dataset(f, root, required=False) is not None for f in folders):
                args.data = name
                break
        else:
            if args.root is not None:
                wanted = " or ".join("/".join(f) for _, f in candidates)
                raise ValidationError(f"--root: expected {wanted} under {root}, found none; pass the folder that "
                                      "holds it, or --data synthetic for the embedded stand-in")
    if args.data is None:
        args.data = "synthetic"
    if args.data != "synthetic":
        args.root = None if root is None else str(root)
        return None
    where = "no data folder given (--root or $NRSFM_DATA)" if root is None else \
        f"{root} holds no {' or '.join('/'.join(f) for _, f in candidates)}"
    return (f"{table}: the embedded synthetic stand-in ({where}): its numbers check the pipeline and the ordering; "
            "they are not comparable with the paper's")


def labels_dir(args: argparse.Namespace) -> Path | None:
    """``--labels-dir`` as a path (None: the table's own ``<out>/labels``)."""
    return Path(args.labels_dir) if getattr(args, "labels_dir", None) else None


def run_table(name: str, run: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """``run(args)`` with INFO logging on stderr; bad input ends in one line ``<name>: error: ...`` and status 2."""
    from nrsfm.errors import NRSfMError

    global _started_from
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
    _started_from = git_hash()
    try:
        return run(args)
    except (NRSfMError, FileNotFoundError, ValueError) as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 2
    finally:
        _started_from = None
