"""Every paper table, one after the other, with one progress display and one summary.

    python -m benchmarks.all [--quick] [--root DIR] [--out DIR] [--tables table1,table2,table_s1,table3,...]
                             [--jobs N] [--device auto|cpu|cuda]

Each table runs as ``python -m benchmarks.<table>`` would, writing its own folder under ``--out``
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
import sys
import time
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.all", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="every table's short schedule on small data")
    p.add_argument("--root", help="data folder (default: $NRSFM_DATA; a table whose data is not there runs on its "
                                  "embedded stand-in)")
    p.add_argument("--out", default=None, help="output folder (default: runs/all[-quick])")
    p.add_argument("--tables", default=",".join(TABLES), help=f"comma-separated among {list(TABLES)}")
    p.add_argument("--jobs", type=int, default=2, help="parallel pseudo-label solves")
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
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(message)s")
    from tqdm.auto import tqdm

    out = Path(args.out or f"runs/all{'-quick' if args.quick else ''}")
    t0 = time.perf_counter()
    summary, failures = [], {}
    bar = tqdm(names, desc="tables", unit="table")
    for name in bar:
        bar.set_postfix_str(name)
        real = has_data(name, args.root)
        folder = out / name
        t = time.perf_counter()
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            rc = importlib.import_module(f"benchmarks.{name}").main(_argv(name, args, real, folder))
        seconds = time.perf_counter() - t
        if rc != 0:
            failures[name] = rc
            summary.append({"table": name, "data": "real" if real else "stand-in", "seconds": seconds, "rc": rc,
                            "rows": []})
            continue
        rows = _rows(name, folder)
        summary.append({"table": name, "data": "real" if real else "stand-in", "seconds": seconds, "rc": 0,
                        "rows": rows, "prn_beats_no_reg": _prn_beats_no_reg(rows)})
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
