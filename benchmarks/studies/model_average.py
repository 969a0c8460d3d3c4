"""PRN-FCN models on one Human3.6M subject: each model, its last iterate, and the mean of their predictions.

    python -m benchmarks.studies.model_average RUN [RUN ...] [--root DIR] [--subject S9] [--input gt-ortho]
                                               [--out DIR]

Each RUN is a cache folder that ``benchmarks.table1`` trained (``<out>/cache/<row>-<hash>/``, holding ``model.pt``
and ``checkpoint.pt``): a PRN-FCN on 2D points (PRN-FCN, PRN-L, a "+NN" row). Every model is scored on the
subject's every frame in PRN's protocol and C3DPO's (:func:`benchmarks.table1.evaluate`,
:func:`benchmarks.table1.evaluate_c3dpo`); a model trained with ``ema`` (:class:`prn.train.TrainConfig`) is scored
beside its last iterate, the live weights of its last checkpoint, which the same run trained: the pair isolates
the averaging from the seed. Then the mean of the models' predictions (normalised shapes, one handedness, as the
labels and the PR loss leave them): how much of the error the models do not share. Nothing is chosen here; the
subject's 3D only scores.
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import markdown_table, run_metadata, run_table, write_json
from nrsfm.errors import ValidationError


def predictions(model, sequences: list) -> list[np.ndarray]:
    """`(F, P, 3)` normalised shapes of ``model`` for each sequence, its frames normalised on their visible points
    as the harness normalises PRN-FCN's test inputs."""
    from prn.data import normalize_2d
    from prn.train import predict

    return [predict(model, normalize_2d(s.points_2d, s.visibility)[0], s.weights) for s in sequences]


def last_iterate(run: Path, model):
    """``model`` with the live weights of ``run``'s last checkpoint (the last iterate of a run that returned an
    average), or None where the run kept the last iterate or has no checkpoint."""
    import torch

    ckpt = run / "checkpoint.pt"
    if not ckpt.is_file():
        return None
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    if not state["config"].get("ema", 0.0):
        return None
    live = copy.deepcopy(model)
    live.load_state_dict(state["model"])
    return live.eval()


def average_rows(runs: list[Path], seqs: list) -> list[list]:
    """[name, MPJPE in PRN's protocol, in C3DPO's] (mm) on ``seqs``: each run's model, its last iterate where it
    returned an average, and the mean of the models' predictions where there are several."""
    from benchmarks.table1 import evaluate, evaluate_c3dpo
    from prn.train import load_model

    rows, kept = [], []

    def score(name: str, preds: list[np.ndarray]) -> None:
        rows.append([name, evaluate(preds, seqs)["Avg"][0], evaluate_c3dpo(preds, seqs)["Avg"][0]])

    for r in runs:
        model = load_model(r / "model.pt", "cpu")
        kept.append(predictions(model, seqs))
        score(r.name, kept[-1])
        live = last_iterate(r, model)
        if live is not None:
            score(f"{r.name}, its last iterate", predictions(live, seqs))
    if len(kept) > 1:
        score(f"mean of the {len(kept)} models' predictions",
              [np.mean([k[i] for k in kept], axis=0) for i in range(len(seqs))])
    return rows


def main(argv: list[str] | None = None) -> int:
    from nrsfm.datasets import find_dataset, h36m

    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.model_average")
    p.add_argument("runs", nargs="+", help="cache folders of benchmarks.table1 (<out>/cache/<row>-<hash>/)")
    p.add_argument("--root", default=None, help="data folder holding h36m/ (default: $NRSFM_DATA)")
    p.add_argument("--subject", default="S9", help="the subject scored (default S9)")
    p.add_argument("--input", default="gt-ortho", choices=("gt-ortho", "gt-persp"))
    p.add_argument("--out", default="runs/model_average")
    args = p.parse_args(argv)

    def run(args: argparse.Namespace) -> int:
        runs = [Path(r) for r in args.runs]
        bad = [str(r) for r in runs if not (r / "model.pt").is_file()]
        if bad:
            raise ValidationError(f"expected cache folders of benchmarks.table1 holding model.pt, got {bad}; give "
                                  "<out>/cache/<row>-<hash>/")
        root = find_dataset("h36m", args.root)
        if not (root / args.subject).is_dir():
            raise ValidationError(f"--subject: expected a folder {root / args.subject}, found none")
        seqs = h36m.load_h36m(root, [args.subject], input=args.input, stride=h36m.detect_stride(root, args.subject),
                              source_fps=50.0)
        rows = average_rows(runs, seqs)
        print(markdown_table(["model", f"{args.subject} MPJPE (mm, PRN protocol)", "C3DPO protocol"], rows))
        write_json(Path(args.out) / "model_average.json",
                   {"meta": run_metadata(runs=[str(r) for r in runs], subject=args.subject, input=args.input),
                    "results": rows})
        return 0

    return run_table("model_average", run, args)


if __name__ == "__main__":
    sys.exit(main())
