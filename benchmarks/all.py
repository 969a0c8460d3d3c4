"""Every paper table, with one progress display and one summary.

    python -m benchmarks.all [--quick] [--root DIR] [--out DIR] [--tables table1,table2,table_s1,table3,...]
                             [--jobs N] [--device auto|cpu|cuda]

With ``--jobs N`` (default 2) the tables run N side by side, each as its own ``python -m benchmarks.<table>``
process with one torch / BLAS thread (its printed table in ``<table>/output.txt``, its messages in
``<table>/stderr.txt``); one thread per table does more work per core than one table on two threads. With
``--jobs 1`` or a single table they run one after the other in this process. Each table writes its own folder
under ``--out``
(``runs/all[-quick]`` by default) with its Markdown, CSV, JSON and figures; trained models and pseudo-labels are
cached there (the pseudo-labels in one folder that every table shares), so an interrupted run resumes where it
stopped. Every table reads the real data it finds under ``--root`` (default ``$NRSFM_DATA``): Human3.6M ``h36m/``
(Table 1 then on all three inputs, GT-ortho, GT-persp and SH) and its frames ``h36m/images/``, ``300vw-3d/`` or
``aflw2000/`` and the frames in ``300vw/``, SURREAL's ``surreal/train`` and ``surreal/test``; where a table's
folder is absent it runs on its embedded stand-in (stated in the summary).

The summary (``summary.md``) lists every row of every table with its number and the paper's, the data each ran
on, its wall time, and whether PRN (PRN-FCN, PRN-CNN) beats PRN w/o reg in that table.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import logging
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

from benchmarks.common import markdown_table, run_metadata, write_json
from nrsfm.datasets import find_dataset

log = logging.getLogger("benchmarks.all")

#: The tables, in the order they run.
TABLES = ("table1", "table2", "table_s1", "table3", "table_s2", "table4")


def datasets(name: str) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The real datasets a table reads: (name, dataset folders), in order of priority."""
    if name in ("table1", "table_s1"):
        return (("h36m", ("h36m",)),)
    return importlib.import_module(f"benchmarks.{name}").SPEC.datasets


def has_data(name: str, root: str | None) -> bool:
    """Whether ``root`` holds the real data of table ``name``."""
    return root is not None and any(all(find_dataset(f, root, required=False) is not None for f in folders)
                                    for _, folders in datasets(name))


def _rows(name: str, folder: Path) -> list[tuple[str, float | None, float | None]]:
    """(row, ours, paper) of a finished table, read back from its JSON."""
    data = json.loads((folder / f"{name}.json").read_text())
    if name == "table1":
        return [(f"{r['method']} ({r['input']}, {r['protocol']} protocol)", r["per_action"]["Avg"]["mpjpe_mm"],
                 r["paper_avg"]) for r in data["results"]]
    if name == "table_s1":
        return [(f"{r['method']} ({100 * r['missing_ratio']:g}% missing, normalised on {r['variant']} points)",
                 r["per_action"]["Avg"]["mpjpe_mm"],
                 r["paper_avg"] if data["meta"]["data"]["data"] == "h36m" else None) for r in data["results"]]
    return [(f"{r['method']} ({r['section']})" if r["section"] else r["method"], r["error"], r["paper"])
            for r in data["results"]]


def _argv(name: str, args: argparse.Namespace, real: bool, out: Path) -> list[str]:
    argv = ["--out", str(out), "--no-progress"]
    if args.quick:
        argv.append("--quick")
    argv += ["--root", args.root] if real else ["--data", "synthetic"]
    if real and name == "table1":
        argv += ["--input", "all"]
    if name != "table_s1":
        argv += ["--jobs", str(args.jobs), "--plots", "--labels-dir", str(out.parent / "labels")]
    argv += ["--device", args.device]
    return argv


def _command(name: str, argv: list[str]) -> list[str]:
    """The command line that runs table ``name`` as its own process."""
    return [sys.executable, "-m", f"benchmarks.{name}", *argv]


#: Thread counts of a table run side by side with others: one thread for torch and every BLAS.
ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}


def _run_process(name: str, argv: list[str]) -> tuple[int, float]:
    """Run table ``name`` in its own one-thread process; its stdout and stderr go to files in its folder.

    Returns (exit status, wall seconds)."""
    folder = Path(argv[argv.index("--out") + 1])
    folder.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    with open(folder / "output.txt", "w") as stdout, open(folder / "stderr.txt", "w") as stderr:
        rc = subprocess.call(_command(name, argv), stdout=stdout, stderr=stderr, env={**os.environ, **ONE_THREAD})
    return rc, time.perf_counter() - t


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.all", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="every table's short schedule on small data")
    p.add_argument("--root", help="data folder (default: $NRSFM_DATA; a table whose data is not there runs on its "
                                  "embedded stand-in)")
    p.add_argument("--out", default=None, help="output folder (default: runs/all[-quick])")
    p.add_argument("--tables", default=",".join(TABLES), help=f"comma-separated among {list(TABLES)}")
    p.add_argument("--jobs", type=int, default=2, help="tables side by side, one thread each (and parallel "
                                                        "pseudo-label solves within a table)")
    p.add_argument("--device", default="auto")
    args = p.parse_args(argv)
    from nrsfm.datasets import data_root

    root = data_root(args.root)
    args.root = None if root is None else str(root)
    names = [t.strip() for t in args.tables.split(",")]
    bad = [t for t in names if t not in TABLES]
    if bad:
        print(f"all: error: --tables: expected names among {list(TABLES)}, got {bad}", file=sys.stderr)
        return 2
    if args.jobs < 1:
        print(f"all: error: --jobs: expected a positive count, got {args.jobs}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(message)s")
    from tqdm.auto import tqdm

    out = Path(args.out or f"runs/all{'-quick' if args.quick else ''}")
    t0 = time.perf_counter()
    side_by_side = args.jobs > 1 and len(names) > 1
    done: dict[str, dict] = {}
    bar = tqdm(total=len(names), desc="tables", unit="table")

    def finish(name: str, real: bool, rc: int, seconds: float) -> None:
        entry = {"table": name, "data": "real" if real else "stand-in", "seconds": seconds, "rc": rc, "rows": []}
        if rc == 0:
            entry["rows"] = _rows(name, out / name)
            entry["prn_beats_no_reg"] = _prn_beats_no_reg(entry["rows"])
        done[name] = entry
        bar.set_postfix_str(name)
        bar.update()

    if side_by_side:
        with ThreadPoolExecutor(args.jobs) as pool:
            futures = {}
            for name in names:
                real = has_data(name, args.root)
                futures[pool.submit(_run_process, name, _argv(name, args, real, out / name))] = (name, real)
            for f in as_completed(futures):
                name, real = futures[f]
                rc, seconds = f.result()
                if rc != 0:
                    print(f"all: {name} exited {rc}; its messages are in {out / name / 'stderr.txt'}",
                          file=sys.stderr)
                finish(name, real, rc, seconds)
    else:
        for name in names:
            real = has_data(name, args.root)
            t = time.perf_counter()
            printed = io.StringIO()
            with contextlib.redirect_stdout(printed):
                rc = importlib.import_module(f"benchmarks.{name}").main(_argv(name, args, real, out / name))
            finish(name, real, rc, time.perf_counter() - t)
    bar.close()
    summary = [done[name] for name in names]
    failures = {s["table"]: s["rc"] for s in summary if s["rc"] != 0}
    total = time.perf_counter() - t0
    text = [f"## All tables{' (--quick)' if args.quick else ''}: {total:.0f} s\n"]
    for s in summary:
        verdict = s.get("prn_beats_no_reg")
        text.append(f"\n### {s['table']} ({s['data']}, {s['seconds']:.0f} s"
                    + (f", exit {s['rc']}: see its own output" if s["rc"] else "")
                    + ("" if verdict is None else f"; PRN beats PRN w/o reg: {'yes' if verdict else 'NO'}")
                    + ")\n")
        if s["rows"]:
            text.append(markdown_table(["row", "ours", "paper"], [list(r) for r in s["rows"]]))
    md = "\n".join(text)
    print(md)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.md").write_text(md + "\n")
    write_json(out / "summary.json", {"meta": run_metadata(tables=names, quick=args.quick, root=args.root,
                                                           total_seconds=total), "tables": summary})
    print(f"\nwrote {out}/summary.md, summary.json and one folder per table ({total:.0f} s)")
    return 1 if failures else 0


def _prn_beats_no_reg(rows) -> bool | None:
    """Whether every PRN-FCN or PRN-CNN row is below the PRN w/o reg row of the same setting (None: no pair)."""
    ours = {r[0]: r[1] for r in rows}
    pairs = [(v, ours.get(k.replace(k[:7], "PRN w/o reg"))) for k, v in ours.items()
             if k.startswith(("PRN-FCN", "PRN-CNN"))]
    pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
    return None if not pairs else all(a < b for a, b in pairs)


if __name__ == "__main__":
    sys.exit(main())
