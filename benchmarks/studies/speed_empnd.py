"""EM-PND on the CPU and on a GPU: time, iterations and e3D of the same solve on each device.

    python -m benchmarks.studies.speed_empnd [--devices cpu,cuda] [--missing 0,0.2] [--frames 1102] [--root DIR]
        [--out DIR]

Sequences: a drink-sized synthetic one (``--frames`` frames, 1102 by default,
x 41 points, K = 5, random cameras, 0.5% 2D noise; always) and CMU drink when the data is found
(``--root`` or ``$NRSFM_DATA``). Each is solved with every fraction of
``--missing`` entries dropped (:func:`nrsfm.datasets.synthetic.drop_entries`) on
every device of ``--devices`` (default: the CPU, and CUDA when torch sees a
GPU). The start (the authors' factorisation with complete tracks,
CSF2-occlusion with missing points) runs on the CPU either way; the table
gives it apart from EM (``info["start_s"]``). An untimed small solve on each
device comes first, so CUDA's start-up is not counted.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

from benchmarks.common import markdown_table, parse_fractions, run_metadata, write_csv, write_json

def drink_sized(n_frames: int = 1102):
    """The drink-sized synthetic sequence (``n_frames`` x 41, K = 5, random cameras, 0.5% 2D noise)."""
    from nrsfm.datasets.synthetic import lowrank_sequence

    return lowrank_sequence(n_frames, 41, 5, noise=0.005, cameras="random", seed=0,
                            name=f"synthetic-lowrank-{n_frames}x41")


def sequences(root: str | None, n_frames: int = 1102) -> list:
    """The drink-sized synthetic sequence, and CMU drink when ``root`` (or ``$NRSFM_DATA``) holds it."""
    import nrsfm

    seqs = [drink_sized(n_frames)]
    base = root or os.environ.get("NRSFM_DATA")
    if base and (Path(base) / "nrsfm" / "drink.mat").is_file():
        seqs.append(nrsfm.load_sequence(Path(base) / "nrsfm" / "drink.mat"))
    return seqs


def measure(seq, missing: float, device: str) -> dict:
    """One EM-PND solve of ``seq`` with ``missing`` of its entries dropped, on ``device``: one result row."""
    import nrsfm
    from nrsfm.datasets.synthetic import drop_entries
    from nrsfm.metrics import e3d

    rec = nrsfm.solve(drop_entries(seq, missing), "empnd", device=device)
    em = rec.runtime_s - rec.info["start_s"]
    return {"sequence": seq.name, "missing": missing, "device": rec.info["device"],
            "threads": torch.get_num_threads(), "seconds": rec.runtime_s, "start_s": rec.info["start_s"],
            "em_s": em, "iterations": rec.iterations, "ms_per_iteration": 1e3 * em / rec.iterations,
            "e3d": float(e3d(rec.points_3d, seq.points_3d)), "cost": rec.info["cost"]}


def main(argv: list[str] | None = None) -> int:
    from nrsfm.errors import NRSfMError

    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.speed_empnd", description=__doc__.split("\n\n")[0])
    p.add_argument("--devices", default="cpu,cuda" if torch.cuda.is_available() else "cpu",
                   help="comma-separated devices (default: cpu, and cuda when torch sees a GPU)")
    p.add_argument("--missing", default="0,0.2", help="comma-separated fractions of entries to drop")
    p.add_argument("--frames", type=int, default=1102, help="frames of the synthetic sequence (default: drink's)")
    p.add_argument("--root", default=None, help="data folder holding nrsfm/drink.mat (default: $NRSFM_DATA)")
    p.add_argument("--out", default="runs/speed_empnd")
    args = p.parse_args(argv)
    try:
        devices = [d.strip() for d in args.devices.split(",") if d.strip()]
        fractions = parse_fractions(args.missing, "--missing")
        if args.frames < 20:
            raise ValueError(f"--frames: expected at least 20, got {args.frames}")
        import nrsfm
        from nrsfm.device import pick_device

        for d in devices:
            pick_device(d)
            nrsfm.solve(drink_sized(30), "empnd", device=d, max_iter=3, init="rigid")  # warm-up
        seqs = sequences(args.root, args.frames)
    except (NRSfMError, ValueError) as exc:
        print(f"speed_empnd: error: {exc}", file=sys.stderr)
        return 2
    rows = [measure(seq, m, d) for seq in seqs for m in fractions for d in devices]
    table = [[r["sequence"], f"{100 * r['missing']:.0f}%", r["device"], r["threads"], f"{r['seconds']:.1f}",
              f"{r['start_s']:.1f}", f"{r['em_s']:.1f}", r["iterations"], f"{r['ms_per_iteration']:.1f}",
              f"{r['e3d']:.5f}"] for r in rows]
    print(markdown_table(["sequence", "missing", "device", "CPU threads", "total (s)", "start (s)", "EM (s)",
                          "iterations", "ms / iteration", "e3D camera"], table))
    out = Path(args.out)
    write_csv(out / "speed_empnd.csv", rows)
    write_json(out / "speed_empnd.json", {"meta": run_metadata(benchmark="EM-PND speed by device"), "rows": rows})
    print(f"\nwrote {out}/speed_empnd.csv, speed_empnd.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
