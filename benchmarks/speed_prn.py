"""Speed of the PR loss and of a PRN training iteration.

    python -m benchmarks.speed_prn [--repeats N] [--device cpu|cuda] [--out DIR]

Measures, for the paper's batch (4 groups x 32 frames x 17 joints, FCN width
1024, float32):

- the PR loss forward + backward alone (on a leaf tensor: alignment, data
  term, nuclear norm, analytic backward);
- a whole training iteration (sampling, network forward, loss, backward,
  Adam step);

and reports the loss's share of the iteration and iterations per second.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import markdown_table, run_metadata, write_json


def _time(fn, repeats: int, sync) -> list[float]:
    for _ in range(3):
        fn()
    out = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        out.append(time.perf_counter() - t0)
    return out


def measure(device: str = "cpu", repeats: int = 50, groups: int = 4, group_size: int = 32, width: int = 1024,
            seed: int = 0) -> dict:
    from nrsfm.datasets.synthetic import human_sequences
    from prn.data import build_training_set
    from prn.loss import pr_loss
    from prn.model import PRNFCN

    dev = torch.device(device)
    sync = (lambda: torch.cuda.synchronize()) if dev.type == "cuda" else (lambda: None)
    torch.manual_seed(seed)
    data = build_training_set(human_sequences(("S1", "S5"), n_frames=200, takes=2))
    rng = np.random.default_rng(seed)
    model = PRNFCN(17, 17, width).to(dev).train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-4, weight_decay=1e-4)
    x_all = torch.as_tensor(data.inputs, dtype=torch.float32, device=dev)
    y_all = torch.as_tensor(data.targets, dtype=torch.float32, device=dev)
    w_all = torch.as_tensor(data.target_weights, dtype=torch.float32, device=dev)

    def iteration():
        idx = torch.as_tensor(data.sample_groups(rng, groups, group_size, 5), device=dev)
        pred = model(x_all[idx])
        loss = pr_loss(pred, y_all[idx], w_all[idx], lam=0.05, group_size=group_size)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    idx = torch.as_tensor(data.sample_groups(rng, groups, group_size, 5), device=dev)
    with torch.no_grad():
        fixed = model(x_all[idx]).detach()

    def loss_only():
        leaf = fixed.clone().requires_grad_(True)
        pr_loss(leaf, y_all[idx], w_all[idx], lam=0.05, group_size=group_size).backward()

    t_iter = _time(iteration, repeats, sync)
    t_loss = _time(loss_only, repeats, sync)
    it, lo = statistics.median(t_iter), statistics.median(t_loss)
    return {"device": str(dev), "threads": torch.get_num_threads(), "batch": f"{groups} x {group_size} x 17",
            "width": width, "iteration_ms": 1e3 * it, "loss_fwd_bwd_ms": 1e3 * lo, "loss_share": lo / it,
            "iterations_per_second": 1 / it, "repeats": repeats}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.speed_prn")
    p.add_argument("--repeats", type=int, default=50)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--out", default="runs/speed_prn")
    args = p.parse_args(argv)
    r = measure(args.device, args.repeats)
    print(markdown_table(["device", "threads", "batch", "iteration (ms)", "PR loss fwd+bwd (ms)", "loss share",
                          "iterations/s"],
                         [[r["device"], r["threads"], r["batch"], r["iteration_ms"], r["loss_fwd_bwd_ms"],
                           f"{100 * r['loss_share']:.1f}%", r["iterations_per_second"]]]))
    write_json(Path(args.out) / "speed_prn.json", {"meta": run_metadata(), "result": r})
    return 0


if __name__ == "__main__":
    sys.exit(main())
