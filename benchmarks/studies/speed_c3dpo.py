"""Speed of a C3DPO training iteration in float32 and with bfloat16 trunks, launched op by op or replayed as a
CUDA graph, and compiled by ``torch.compile``.

    python -m benchmarks.studies.speed_c3dpo [--batch 256] [--repeats N] [--warmup N] [--device cpu|cuda]
                                             [--precision fp32|bf16] [--eager-only] [--compile] [--out DIR]

Times whole training iterations (the authors' model: two 1024-wide trunks of 6 bottleneck blocks, 17 keypoints,
the in-plane augmentation, the canonicalisation loss on 4 rotated copies, SGD) on random centred keypoints, for
``precision="fp32"`` and ``"bf16"`` (:class:`baselines.c3dpo.C3DPOConfig`), after an untimed warm-up; on a CUDA
device also as CUDA graphs (:class:`baselines.c3dpo.TrainStep`); with ``--compile`` also compiled (as CUDA graphs
on a CUDA device; the warm-up compiles, untimed). Reports the median iteration time, iterations per second and each
row's speed-up over the first row (op by op, the first precision); the thread count is torch's (set it with
``OMP_NUM_THREADS``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from benchmarks.common import markdown_table, run_metadata, write_json


def measure(precision: str, device: str = "cpu", batch: int = 256, repeats: int = 20, warmup: int = 3,
            seed: int = 0, cuda_graph: bool = False, compile: bool = False) -> dict:
    """Median seconds of one training iteration of batch ``batch`` at ``precision`` (as a CUDA graph when
    ``cuda_graph``, compiled when ``compile``); ``warmup_s``: the warm-up's seconds (the compilation)."""
    import numpy as np

    from baselines.c3dpo import C3DPO, C3DPOConfig, TrainStep, make_optimizer

    dev = torch.device(device)
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    config = C3DPOConfig(batch=batch, precision=precision)
    model = C3DPO(17, config).to(dev).train()
    step = TrainStep(model, make_optimizer(model, config), torch.randn(4 * batch, 2, 17, device=dev) * 0.25,
                     torch.ones(4 * batch, 17, device=dev), batch, cuda_graph, compile)

    def iteration() -> float:
        sync()
        t0 = time.perf_counter()
        step(rng.integers(0, 4 * batch, batch), config.lr)
        sync()
        return time.perf_counter() - t0

    t0 = time.perf_counter()
    for _ in range(warmup):
        iteration()
    warm = time.perf_counter() - t0
    it = statistics.median(iteration() for _ in range(repeats))
    return {"precision": precision, "cuda_graph": cuda_graph, "compile": compile, "device": str(dev),
            "threads": torch.get_num_threads(), "batch": batch, "warmup_s": warm, "iteration_s": it,
            "iterations_per_second": 1 / it, "repeats": repeats, "warmup": warmup}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.speed_c3dpo")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3, help="untimed iterations first")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--eager-only", action="store_true", help="on a CUDA device too, time op-by-op launches only")
    p.add_argument("--precision", choices=["fp32", "bf16"], action="append",
                   help="time this precision (repeat for several; default both)")
    p.add_argument("--compile", action="store_true", help="also time the iteration compiled by torch.compile")
    p.add_argument("--out", default="runs/speed_c3dpo")
    args = p.parse_args(argv)
    if args.batch < 2 or args.repeats < 1 or args.warmup < 0:
        p.error(f"expected --batch >= 2, --repeats >= 1, --warmup >= 0, got {args.batch}, {args.repeats}, "
                f"{args.warmup}")
    graphs = (False, True) if torch.device(args.device).type == "cuda" and not args.eager_only else (False,)
    precisions = args.precision or ["fp32", "bf16"]
    variants = [(g, False) for g in graphs] + ([(graphs[-1], True)] if args.compile else [])
    rows = [measure(prec, args.device, args.batch, args.repeats, args.warmup, cuda_graph=g, compile=c)
            for g, c in variants for prec in precisions]
    for r in rows:
        r["speedup"] = rows[0]["iteration_s"] / r["iteration_s"]
    print(markdown_table(["precision", "CUDA graph", "compiled", "device", "threads", "batch", "warm-up (s)",
                          "iteration (s)", "iterations/s", "times faster than the first row"],
                         [[r["precision"], "yes" if r["cuda_graph"] else "no", "yes" if r["compile"] else "no",
                           r["device"], r["threads"], r["batch"], r["warmup_s"], r["iteration_s"],
                           r["iterations_per_second"], r["speedup"]] for r in rows]))
    write_json(Path(args.out) / "speed_c3dpo.json", {"meta": run_metadata(), "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
