"""The built-in rows: PRN-FCN and PRN without regularisation (lambda = 0)."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np

from benchmarks.registry import RunContext, Split, register_method, scaled_schedule

log = logging.getLogger(__name__)


def _train_prn(split: Split, ctx: RunContext, name: str, lam: float) -> list[np.ndarray]:
    from prn.data import build_training_set
    from prn.train import load_model, predict, train

    data = build_training_set(split.train_inputs, split.train_targets, sampling=split.sampling)
    config = scaled_schedule(ctx.iterations, lam=lam, seed=ctx.seed, device=ctx.device)
    cache = ctx.cache_dir(name, {"config": dataclasses.asdict(config), "data": split.tag,
                                 "input": split.input_type, "frames": data.description})
    model_path = cache / "model.pt"
    if model_path.exists() and not ctx.retrain:
        log.info("%s: using the cached model %s", name, model_path)
        model = load_model(model_path, ctx.device)
        info = json.loads((cache / "train.json").read_text())
        ctx.timings[f"{name} ({split.input_type})"] = {"cached": True, "train_seconds": info["seconds"],
                                                       "iterations": info["iterations_run"], "cache": str(cache)}
    else:
        res = train(data, config, cache, resume=not ctx.retrain, progress=ctx.progress)
        model = res.model
        ctx.timings[f"{name} ({split.input_type})"] = {
            "cached": False, "train_seconds": res.seconds, "iterations": res.iterations_run,
            "iterations_per_second": res.iterations_per_second, "cache": str(cache)}
    out = []
    for seq in split.test_inputs:
        x, w = data.prepare_inputs(seq)
        out.append(predict(model, x, w))
    return out


@register_method("PRN-FCN", ("gt-ortho", "gt-persp", "sh"), "PRN-FCN trained with the PR loss, lambda = 0.05")
def prn_fcn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _train_prn(split, ctx, "PRN-FCN", 0.05)


@register_method("PRN w/o reg", ("gt-ortho", "gt-persp", "sh"), "the same network and data term, lambda = 0")
def prn_no_reg(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _train_prn(split, ctx, "PRN w/o reg", 0.0)
