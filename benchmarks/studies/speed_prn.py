"""Speed of the PR loss and of a PRN training iteration.

    python -m benchmarks.studies.speed_prn [--repeats N] [--warmup N] [--device cpu|cuda] [--out DIR]

Measures, for the paper's batch (4 groups x 32 frames x 17 joints, FCN width
1024, float32):

- whole training iterations (sampling, network forward, loss, backward,
  Adam step), after an untimed warm-up of training;
- inside each, the PR loss forward + backward (alignment, data term,
  nuclear norm, analytic backward);

and reports the loss's share of the iteration time (total loss time over
total iteration time), the medians, iterations per second and the median
number of alignment steps.
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


def measure(device: str = "cpu", repeats: int = 50, groups: int = 4, group_size: int = 32, width: int = 1024,
            seed: int = 0, warmup_iterations: int = 200, align_device: str | None = None) -> dict:
    """Time training iterations and, inside each, the PR loss's forward + backward.

    Each iteration is split into network forward, loss forward + backward (on
    a detached copy of the prediction; numerically the same iteration), the
    network's backward from that gradient, and the Adam step, so the loss's
    share is measured on the shapes training actually produces. The first
    ``warmup_iterations`` train the network (untimed) so that the shapes are
    not those of an untrained network.
    """
    from nrsfm.datasets.synthetic import human_sequences
    from prn.data import build_training_set
    from prn.loss import PRLossParts, pr_loss
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
    parts = PRLossParts()

    def iteration() -> tuple[float, float, int]:
        sync()
        t0 = time.perf_counter()
        idx = torch.as_tensor(data.sample_groups(rng, groups, group_size, 5), device=dev)
        pred = model(x_all[idx])
        leaf = pred.detach().requires_grad_(True)
        sync()
        t1 = time.perf_counter()
        loss = pr_loss(leaf, y_all[idx], w_all[idx], lam=0.05, group_size=group_size, parts=parts,
                       align_device=align_device)
        loss.backward()
        sync()
        t2 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        pred.backward(leaf.grad)
        opt.step()
        sync()
        t3 = time.perf_counter()
        return t3 - t0, t2 - t1, parts.align_iterations

    for _ in range(warmup_iterations):
        iteration()
    samples = [iteration() for _ in range(repeats)]
    it = statistics.median(s[0] for s in samples)
    lo = statistics.median(s[1] for s in samples)
    share = sum(s[1] for s in samples) / sum(s[0] for s in samples)
    return {"device": str(dev), "align_device": align_device or str(dev), "threads": torch.get_num_threads(),
            "batch": f"{groups} x {group_size} x 17",
            "width": width, "iteration_ms": 1e3 * it, "loss_fwd_bwd_ms": 1e3 * lo, "loss_share": share,
            "iterations_per_second": 1 / it, "align_steps_median": statistics.median(s[2] for s in samples),
            "repeats": repeats, "warmup_iterations": warmup_iterations}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.speed_prn")
    p.add_argument("--repeats", type=int, default=100)
    p.add_argument("--warmup", type=int, default=200, help="untimed training iterations first")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--align-device", default=None, help="where the PR loss's alignment runs (default: --device)")
    p.add_argument("--out", default="runs/speed_prn")
    args = p.parse_args(argv)
    r = measure(args.device, args.repeats, warmup_iterations=args.warmup, align_device=args.align_device)
    print(markdown_table(["device", "loss alignment on", "threads", "batch", "iteration (ms)", "PR loss fwd+bwd (ms)",
                          "loss share", "iterations/s", "alignment steps"],
                         [[r["device"], r["align_device"], r["threads"], r["batch"], r["iteration_ms"],
                           r["loss_fwd_bwd_ms"], f"{100 * r['loss_share']:.1f}%", r["iterations_per_second"],
                           r["align_steps_median"]]]))
    write_json(Path(args.out) / "speed_prn.json", {"meta": run_metadata(), "result": r})
    return 0


if __name__ == "__main__":
    sys.exit(main())
