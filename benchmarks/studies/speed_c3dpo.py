"""Speed of a C3DPO training iteration in float32 and with bfloat16 trunks.

    python -m benchmarks.studies.speed_c3dpo [--batch 256] [--repeats N] [--warmup N] [--device cpu|cuda]
                                             [--out DIR]

Times whole training iterations (the authors' model: two 1024-wide trunks of 6 bottleneck blocks, 17 keypoints,
the in-plane augmentation, the canonicalisation loss on 4 rotated copies, SGD) on random centred keypoints, for
``precision="fp32"`` and ``"bf16"`` (:class:`baselines.c3dpo.C3DPOConfig`), after an untimed warm-up. Reports the
median iteration time, iterations per second and the speed-up; the thread count is torch's (set it with
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
            seed: int = 0) -> dict:
    """Median seconds of one training iteration of batch ``batch`` at ``precision``."""
    from baselines.c3dpo import C3DPO, C3DPOConfig, make_optimizer, training_losses

    dev = torch.device(device)
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    torch.manual_seed(seed)
    config = C3DPOConfig(batch=batch, precision=precision)
    model = C3DPO(17, config).to(dev).train()
    opt = make_optimizer(model, config)
    w = torch.randn(batch, 2, 17, device=dev) * 0.25
    v = torch.ones(batch, 17, device=dev)

    def iteration() -> float:
        sync()
        t0 = time.perf_counter()
        loss_rep, loss_can = training_losses(model, w, v)
        opt.zero_grad(set_to_none=True)
        (loss_rep + loss_can).backward()
        opt.step()
        sync()
        return time.perf_counter() - t0

    for _ in range(warmup):
        iteration()
    it = statistics.median(iteration() for _ in range(repeats))
    return {"precision": precision, "device": str(dev), "threads": torch.get_num_threads(), "batch": batch,
            "iteration_s": it, "iterations_per_second": 1 / it, "repeats": repeats, "warmup": warmup}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.speed_c3dpo")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3, help="untimed iterations first")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--out", default="runs/speed_c3dpo")
    args = p.parse_args(argv)
    if args.batch < 2 or args.repeats < 1 or args.warmup < 0:
        p.error(f"expected --batch >= 2, --repeats >= 1, --warmup >= 0, got {args.batch}, {args.repeats}, "
                f"{args.warmup}")
    rows = [measure(prec, args.device, args.batch, args.repeats, args.warmup) for prec in ("fp32", "bf16")]
    speedup = rows[0]["iteration_s"] / rows[1]["iteration_s"]
    print(markdown_table(["precision", "device", "threads", "batch", "iteration (s)", "iterations/s"],
                         [[r["precision"], r["device"], r["threads"], r["batch"], r["iteration_s"],
                           r["iterations_per_second"]] for r in rows]))
    print(f"\nbf16 trunks: {speedup:.2f} times faster")
    write_json(Path(args.out) / "speed_c3dpo.json", {"meta": run_metadata(), "results": rows, "speedup": speedup})
    return 0


if __name__ == "__main__":
    sys.exit(main())
