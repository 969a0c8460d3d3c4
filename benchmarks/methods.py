"""The built-in rows: PRN-FCN, PRN without regularisation (lambda = 0), the "+NN" baselines on pseudo-labels,
GT 3D and C3DPO; on image input (``rgb``) PRN-CNN, the "+CNN" baselines, and PRN w/o reg and GT 3D with the same
CNN."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np

from benchmarks.registry import (Method, NotRun, Predictions, RunContext, Split, millimetres, register_method,
                                 registered, schedule)
from nrsfm.errors import ValidationError

log = logging.getLogger(__name__)


def _network(split: Split, ctx: RunContext) -> str:
    """PRN-FCN on 2D input; on ``rgb`` input the context's CNN backbone."""
    if split.input_type != "rgb":
        return "fcn"
    if split.train_images is None or split.test_images is None:
        raise ValueError("rgb input: the split carries no images")
    return ctx.network


def cache_config(config) -> dict:
    """A :class:`~prn.train.TrainConfig` as a cache key: its fields, but the later ones (missing points' data term
    and normalisation, pseudo-labels, weight averaging) only where they are not the default (so that models cached
    before the options existed stay valid)."""
    out = dataclasses.asdict(config)
    for name, default in (("missing_in_loss", True), ("missing_normalise", "all"), ("label_weight", 0.0),
                          ("label_decay", "none"), ("ema", 0.0)):
        if out[name] == default:
            del out[name]
    if "ema" in out:  # the average spans the steps after the BN freeze and keeps the frozen statistics
        out["ema_from"] = "bn-freeze"
    return out


#: PRN-L's weight average (:attr:`prn.train.TrainConfig.ema`), chosen on S8 held out against the same runs' last
#: iterates (benchmarks/RESULTS.md, PRN-L). The other rows keep the paper's last iterate.
PRN_L_EMA = 0.999

#: PRN-L averages each test frame's shape with its mirror image's (:func:`prn.train.predict_mirrored`), chosen on
#: S8 held out (benchmarks/RESULTS.md, PRN-L); the other rows predict as the paper.
PRN_L_MIRROR_TEST = True

#: PRN-L trains on the training frames and their mirror images (:func:`prn.data.mirror_sequence`, labels mirrored
#: with them), chosen on S8 held out (benchmarks/RESULTS.md, PRN-L).
PRN_L_MIRROR_TRAIN = True

#: PRN-L solves its pseudo-labels from the 2D its data term compares with (on SH the ground-truth 2D the paper's SH
#: networks are trained against, not the detections they read), chosen on S8 held out (benchmarks/RESULTS.md,
#: PRN-L); the "+NN" rows solve them from their inputs.
PRN_L_LABEL_SOURCE = "targets"


def _config(ctx: RunContext, network: str, lam: float, ema: float = 0.0, **extra):
    """The PRN recipe of ``ctx`` (:func:`benchmarks.registry.schedule`): iterations, schedule, alignment groups,
    width, missing points and where they are normalised, weight averaging (``ctx.ema``, else the row's ``ema``)."""
    missing = {"missing_points": ctx.missing_points}
    if ctx.missing_points > 0:
        missing["missing_normalise"] = ctx.normalise_on
    return schedule(ctx.iterations, ctx.compress_schedule, lam=lam, seed=ctx.seed, device=ctx.device, width=ctx.width,
                    groups=ctx.groups, group_size=ctx.group_size, network=network,
                    ema=ema if ctx.ema is None else ctx.ema, **missing, **extra)


def _with_mirror_images(inputs: list, targets: list | None, network: str) -> tuple[list, list | None, np.ndarray]:
    """``--mirror-train``: the training sequences followed by their mirror images (:func:`prn.data.mirror_sequence`),
    inputs and 2D targets alike, and the `(P,)` output permutation (to mirror the sequences' labels with them)."""
    from prn.data import mirror_permutation, mirror_sequence

    if network != "fcn":
        raise NotRun("--mirror-train: mirrored images are not built; train the 2D networks with it")
    perm = mirror_permutation(inputs[0].joint_names)
    if perm is None:
        raise NotRun("--mirror-train: the joint names pair no left and right joints")
    return (inputs + [mirror_sequence(s, perm) for s in inputs],
            None if targets is None else targets + [mirror_sequence(s, perm) for s in targets], perm)


def _predict(model, data, split: Split, ctx: RunContext, name: str = "", mirror: bool = False) -> Predictions:
    """The test predictions; inputs normalised on their visible points where training points went missing and
    were normalised the same way, scaled back by the ground truth's statistic over those points. ``mirror``:
    each frame's shape averaged with its mirror image's (:func:`prn.train.predict_mirrored`), where the joint
    names pair left and right."""
    from prn.data import denormalize, mirror_perms
    from prn.train import predict, predict_images, predict_mirrored

    if split.input_type == "rgb":
        return Predictions(predict_images(model, im) for im in split.test_images)
    perms = mirror_perms(split.test_inputs[0].joint_names, data.input_points) if mirror else None
    if mirror:
        ctx.timings.setdefault(f"{name} ({split.input_type})", {})["mirror_test"] = perms is not None
        if perms is None:
            log.warning("%s: no test-time mirroring: the joint names pair no left and right joints", name)
    inputs = (data.prepare_inputs(seq, ctx.normalise_on) for seq in split.test_inputs)
    out = Predictions(predict(model, *x) if perms is None else predict_mirrored(model, *x, *perms) for x in inputs)
    if ctx.missing_points > 0 and ctx.normalise_on == "visible":
        out.millimetres = [denormalize(p, t.points_3d, s.weights > 0)
                           for p, s, t in zip(out, split.test_inputs, split.test_truth)]
    return out


def _train_prn(split: Split, ctx: RunContext, name: str, lam: float, scores: bool = False,
               labels: tuple[np.ndarray, dict] | None = None) -> list[np.ndarray]:
    """PRN (``lam`` > 0) or PRN w/o reg; ``scores``: detection scores weigh the data term; ``labels``: normalised
    pseudo-labels (one per training frame) and their cache key, pulled towards with ``ctx.label_weight`` (PRN-L,
    whose weights are averaged, :data:`PRN_L_EMA`, unless ``ctx.ema`` says otherwise)."""
    from prn.data import build_training_set, mirror_points
    from prn.train import load_model, train

    network = _network(split, ctx)
    inputs, targets = split.train_inputs, split.train_targets
    mirror_train = (labels is not None and PRN_L_MIRROR_TRAIN) if ctx.mirror_train is None else ctx.mirror_train
    if mirror_train:
        inputs, targets, perm = _with_mirror_images(inputs, targets, network)
        if labels is not None:
            labels = (np.concatenate([labels[0], mirror_points(labels[0], perm)]), {**labels[1], "mirrored": True})
    data = build_training_set(inputs, targets, sampling=split.sampling,
                              images=split.train_images if network != "fcn" else None, scores=scores)
    extra = {} if labels is None else {"label_weight": ctx.label_weight, "label_decay": ctx.label_decay,
                                       "ema": PRN_L_EMA}
    config = _config(ctx, network, lam, missing_in_loss=ctx.missing_in_loss, point_groups=ctx.point_groups, **extra)
    key = {"config": cache_config(config), "data": split.tag, "input": split.input_type, "frames": data.description}
    if scores:
        key["scores"] = True
    if mirror_train:
        key["mirror_train"] = True
    if labels is not None:
        key["labels"] = labels[1]
    cache = ctx.cache_dir(name, key)
    model_path = cache / "model.pt"
    if model_path.exists() and not ctx.retrain:
        log.info("%s: using the cached model %s", name, model_path)
        model = load_model(model_path, ctx.device)
        info = json.loads((cache / "train.json").read_text())
        ctx.timings.setdefault(f"{name} ({split.input_type})", {}).update(  # beside the labels' summary
            {"cached": True, "train_seconds": info["seconds"], "iterations": info["iterations_run"],
             "cache": str(cache)})
    else:
        res = train(data, config, cache, resume=not ctx.retrain, progress=ctx.progress,
                    labels=None if labels is None else labels[0])
        model = res.model
        ctx.timings.setdefault(f"{name} ({split.input_type})", {}).update(
            {"cached": False, "train_seconds": res.seconds, "iterations": res.iterations_run,
             "iterations_per_second": res.iterations_per_second, "cache": str(cache)})
    ctx.timings[f"{name} ({split.input_type})"]["mirror_train"] = mirror_train
    mirror = (labels is not None and PRN_L_MIRROR_TEST) if ctx.mirror_test is None else ctx.mirror_test
    return _predict(model, data, split, ctx, name, mirror)


@register_method("PRN-FCN", ("gt-ortho", "gt-persp", "sh"), "PRN-FCN trained with the PR loss, lambda = 0.05")
def prn_fcn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _train_prn(split, ctx, "PRN-FCN", 0.05)


def has_scores(seqs: list) -> bool:
    """Whether the detections carry per-point scores: a visibility strictly between 0 and 1 somewhere."""
    return any(s.visibility is not None and bool(((s.visibility > 0) & (s.visibility < 1)).any()) for s in seqs)


@register_method("PRN-FCN-W", ("sh",), "PRN-FCN whose data term weighs each point by its detection score (the "
                                       "input's visibility in (0, 1])")
def prn_fcn_w(split: Split, ctx: RunContext) -> list[np.ndarray]:
    if not has_scores(split.train_inputs):
        raise NotRun("these detections carry no scores (every visibility is 0 or 1)")
    return _train_prn(split, ctx, "PRN-FCN-W", 0.05, scores=True)


@register_method("PRN-CNN", ("rgb",), "PRN-CNN (image backbone + PRN-FCN's head) trained with the PR loss, "
                                      "lambda = 0.05")
def prn_cnn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _train_prn(split, ctx, "PRN-CNN", 0.05)


@register_method("PRN w/o reg", ("gt-ortho", "gt-persp", "sh", "rgb"), "the same network and data term, lambda = 0")
def prn_no_reg(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _train_prn(split, ctx, "PRN w/o reg", 0.0)


# --------------------------------------------------------------------------- baselines
def _cached_supervised(split: Split, ctx: RunContext, name: str, shapes: list[np.ndarray], key: dict
                       ) -> list[np.ndarray]:
    """PRN-FCN trained on ``shapes`` with the supervised 3D loss (:mod:`baselines.supervised`), cached by
    configuration and ``key`` (what the shapes are), then run on the test inputs."""
    from baselines.supervised import train_supervised
    from prn.data import build_training_set, mirror_points
    from prn.train import load_model

    network = _network(split, ctx)
    images = split.train_images if network != "fcn" else None
    config = _config(ctx, network, 0.0)
    inputs, targets = split.train_inputs, split.train_targets
    cache_key = {"config": cache_config(config), "data": split.tag, "input": split.input_type, "targets": key}
    if ctx.mirror_train:
        inputs, targets, perm = _with_mirror_images(inputs, targets, network)
        shapes = list(shapes) + [mirror_points(x, perm) for x in shapes]
        cache_key["mirror_train"] = True
    cache = ctx.cache_dir(name, cache_key)
    model_path = cache / "model.pt"
    if model_path.exists() and not ctx.retrain:
        log.info("%s: using the cached model %s", name, model_path)
        model = load_model(model_path, ctx.device)
        data = build_training_set(inputs, targets, sampling="random")  # for test inputs
        info = json.loads((cache / "train.json").read_text())
        ctx.timings.setdefault(f"{name} ({split.input_type})", {}).update(
            {"cached": True, "train_seconds": info["seconds"], "iterations": info["iterations_run"],
             "cache": str(cache)})
    else:
        res, data = train_supervised(inputs, shapes, config, cache, targets_2d=targets,
                                     resume=not ctx.retrain, progress=ctx.progress, images=images)
        model = res.model
        ctx.timings.setdefault(f"{name} ({split.input_type})", {}).update(
            {"cached": False, "train_seconds": res.seconds, "iterations": res.iterations_run,
             "iterations_per_second": res.iterations_per_second, "cache": str(cache)})
    ctx.timings[f"{name} ({split.input_type})"]["mirror_train"] = bool(ctx.mirror_train)
    return _predict(model, data, split, ctx, name, bool(ctx.mirror_test))


def pseudo_labels(split: Split, ctx: RunContext, name: str, solver: str,
                  source: str = "inputs") -> tuple[list[np.ndarray], dict]:
    """Pseudo-labels of ``solver`` on the training inputs, or on the 2D targets of the data term with ``source``
    "targets" (``ctx.label_source`` overrides; :mod:`baselines.labels`; perspective tracks as weak-perspective ones,
    each frame scaled to a unit xy norm when ``ctx.label_frames`` is "unit"), one `(F, P, 3)` array per training
    sequence, and their cache key; the label summary goes to ``ctx.timings``. Solvers joined by "+"
    (``"pr+empnd"``) give the equal-weight mean of their label sets (:mod:`baselines.label_mix`)."""
    from baselines.label_mix import mix_labels, parse_label_solvers
    from baselines.labels import code_version, make_labels
    from prn.data import unit_frames

    source = ctx.label_source or source
    targets = source == "targets" and split.train_targets is not split.train_inputs
    tracks = [s.to_weak_perspective() if s.projection == "perspective" else s
              for s in (split.train_targets if targets else split.train_inputs)]
    dataset = split.labels_tag or split.tag
    if targets:
        dataset = split.targets_labels_tag or dataset + "-targets"
    if ctx.label_frames == "unit":
        tracks, dataset = [unit_frames(s) for s in tracks], dataset + "-unit-frames"
    sets = [make_labels(tracks, part, ctx.label_params.get(part),
                        out_dir=ctx.labels_dir or ctx.out_dir / "labels", dataset=dataset,
                        jobs=ctx.jobs, progress=ctx.progress, truth=split.train_targets)
            for part in parse_label_solvers(solver)]
    labels = sets[0] if len(sets) == 1 else mix_labels(sets, truth=split.train_targets)
    s = labels.summary
    s["label_mpjpe_mm"], s["frames_solved"], s["source"] = s["label_mpjpe"], ctx.label_frames, source
    log.info("%s: labels from %s: %d cuts, %d failed, %d of %d frames labelled, label MPJPE %s (the ground "
             "truth's units: mm on Human3.6M), %.0f s", name,
             solver, s["cuts"], s["failed"], s["labelled_frames"], s["frames"],
             f"{s['label_mpjpe_mm']:.1f}" if s["label_mpjpe_mm"] is not None else "-", s["seconds"])
    ctx.timings.setdefault(f"{name} ({split.input_type})", {})["labels"] = s
    key = {"solver": solver, "params": s["params"], "code": code_version(), "gap": s["gap"]}
    if "weights" in s:
        key["weights"] = s["weights"]
    if ctx.label_frames != "as-is":
        key["frames"] = ctx.label_frames
    if targets:
        key["source"] = "targets"
    return labels.labels, key


def _plus_nn(split: Split, ctx: RunContext, name: str, solver: str) -> list[np.ndarray]:
    """A "+NN" row: pseudo-labels of ``solver`` on the training inputs, then the supervised network."""
    labels, key = pseudo_labels(split, ctx, name, solver)
    return _cached_supervised(split, ctx, name, labels, key)


@register_method("PRN-L", ("gt-ortho", "gt-persp", "sh"),
                 "PRN-FCN trained with the PR loss and a pull towards per-sequence NRSfM pseudo-labels (EM-PND's "
                 "by default): no 3D ground truth")
def prn_l(split: Split, ctx: RunContext) -> list[np.ndarray]:
    from baselines.supervised import normalised_targets

    labels, key = pseudo_labels(split, ctx, "PRN-L", ctx.label_solver, PRN_L_LABEL_SOURCE)
    return _train_prn(split, ctx, "PRN-L", 0.05, labels=(normalised_targets(labels), key))


@register_method("CSF2 + NN", ("gt-ortho",), "PRN-FCN's network on CSF2's pseudo-3D labels (supervised)")
def csf2_nn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _plus_nn(split, ctx, "CSF2 + NN", "csf2")


@register_method("SPM + NN", ("gt-ortho",), "PRN-FCN's network on SPM's pseudo-3D labels (supervised)")
def spm_nn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _plus_nn(split, ctx, "SPM + NN", "spm")


@register_method("PR + NN", ("gt-ortho", "gt-persp", "sh"),
                 "PRN-FCN's network on PR's pseudo-3D labels (supervised; on every input, beside PRN-L, which "
                 "reads the same labels)")
def pr_nn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _plus_nn(split, ctx, "PR + NN", "pr")


@register_method("EM-PND + NN", ("gt-ortho",), "PRN-FCN's network on EM-PND's pseudo-3D labels (supervised)")
def empnd_nn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _plus_nn(split, ctx, "EM-PND + NN", "empnd")


@register_method("CSF2 + CNN", ("rgb",), "PRN-CNN's network on CSF2's pseudo-3D labels (supervised)")
def csf2_cnn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _plus_nn(split, ctx, "CSF2 + CNN", "csf2")


@register_method("SPM + CNN", ("rgb",), "PRN-CNN's network on SPM's pseudo-3D labels (supervised)")
def spm_cnn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _plus_nn(split, ctx, "SPM + CNN", "spm")


@register_method("PR + CNN", ("rgb",), "PRN-CNN's network on PR's pseudo-3D labels (supervised)")
def pr_cnn(split: Split, ctx: RunContext) -> list[np.ndarray]:
    return _plus_nn(split, ctx, "PR + CNN", "pr")


@register_method("GT 3D", ("gt-ortho", "gt-persp", "sh", "rgb"), "PRN-FCN's network supervised with ground-truth 3D "
                                                             "(the upper bound)")
def gt_3d(split: Split, ctx: RunContext) -> list[np.ndarray]:
    truth = [s.points_3d for s in split.train_targets]
    if any(t is None for t in truth):
        raise ValueError("GT 3D: the training sequences carry no ground truth 3D")
    return _cached_supervised(split, ctx, "GT 3D", truth, {"targets": "ground truth"})


#: C3DPO's input normalisations: ``"hip"`` (the authors', after Kudo et al.: each frame centred on the hip and
#: divided by its mean hip-to-joint distance), ``"centred"`` (centred, every frame divided by one global scale) and
#: ``"prn"`` (PRN's: each frame centred and divided by its own xy norm).
C3DPO_INPUTS = ("hip", "centred", "prn")


def root_joint(seq) -> int | None:
    """The index of the sequence's ``Hip`` joint, or None (no joint names, or no hip: then the mean of the visible
    points stands in for it)."""
    names = seq.joint_names or ()
    return list(names).index("Hip") if "Hip" in names else None


def hip_frame(points: np.ndarray, weights: np.ndarray, root: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Kudo et al.'s per-frame normalisation, which C3DPO's Human3.6M data used for its 2D inputs and, computed on
    the 3D, to turn its errors into millimetres: the root joint's xy `(F, 1, 2)` (the mean of the visible points
    where the root is None or hidden) and `(F,)` the mean xy distance of the other visible points to it.

    Args:
        points: `(F, P, 2)` or `(F, P, 3)` (only x, y are read); weights: `(F, P)` (0 = missing).
    """
    xy = np.nan_to_num(np.asarray(points, dtype=np.float64)[..., :2])
    vis = np.asarray(weights) > 0
    centre = (xy * vis[..., None]).sum(axis=1, keepdims=True) / np.maximum(vis.sum(axis=1), 1)[:, None, None]
    others = vis.copy()
    if root is not None:
        has_root = vis[:, root]
        centre = np.where(has_root[:, None, None], xy[:, root:root + 1], centre)
        others[:, root] &= ~has_root
    dist = np.linalg.norm(xy - centre, axis=2)
    scale = (dist * others).sum(axis=1) / np.maximum(others.sum(axis=1), 1)
    return centre, np.where(scale > 0, scale, 1.0)


def c3dpo_unit(train_inputs: list, inputs: str = "hip") -> float:
    """The one global scale of ``"centred"`` inputs (:data:`C3DPO_INPUTS`): the training frames' median xy norm;
    1 for the per-frame normalisations."""
    from prn.data import normalize_2d

    if inputs not in C3DPO_INPUTS:
        raise ValueError(f"c3dpo_inputs: expected one of {C3DPO_INPUTS}, got {inputs!r}")
    if inputs != "centred":
        return 1.0
    return float(np.median(np.concatenate([normalize_2d(s.points_2d, s.visibility)[1] for s in train_inputs])))


def c3dpo_inputs(seqs: list, unit: float, inputs: str = "hip") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(N, P, 2)` keypoints, `(N, P)` weights and `(N,)` per-frame scales of ``seqs`` as C3DPO reads them
    (:data:`C3DPO_INPUTS`): every point, the never-detected ones zero with visibility 0; a keypoint times its
    frame's scale is back in the data's units."""
    from prn.data import normalize_2d

    w = np.concatenate([s.weights for s in seqs])
    if inputs == "prn":
        x, scale = zip(*(normalize_2d(s.points_2d, s.visibility) for s in seqs))
        return np.concatenate(x), w, np.concatenate(scale)
    pts = np.nan_to_num(np.concatenate([s.points_2d for s in seqs])) * (w > 0)[..., None]
    if inputs == "centred":
        return pts / unit, w, np.full(len(pts), unit)
    out, scales = [], []
    for s in seqs:
        centre, scale = hip_frame(s.points_2d, s.weights, root_joint(s))
        out.append((np.nan_to_num(s.points_2d) - centre) / scale[:, None, None] * (s.weights > 0)[..., None])
        scales.append(scale)
    return np.concatenate(out), w, np.concatenate(scales)


def _c3dpo_shapes(model, seq, unit: float, inputs: str, replace_keypoints_with_input: bool = True
                  ) -> tuple[np.ndarray, np.ndarray]:
    """`(F, P, 3)` shapes of C3DPO ``model`` for ``seq`` in its input units, and `(F,)` those units' scales."""
    from baselines.c3dpo import predict_c3dpo

    x, w, scale = c3dpo_inputs([seq], unit, inputs)
    return predict_c3dpo(model, x, w, replace_keypoints_with_input=replace_keypoints_with_input), scale


def c3dpo_predict(model, seq, unit: float, inputs: str = "hip", replace_keypoints_with_input: bool = True
                  ) -> np.ndarray:
    """`(F, P, 3)` shapes of C3DPO ``model`` for ``seq``, in PRN's per-frame units (as the harness scores them;
    ``replace_keypoints_with_input``: :func:`baselines.c3dpo.predict_c3dpo`)."""
    from prn.data import normalize_2d

    pred, scale = _c3dpo_shapes(model, seq, unit, inputs, replace_keypoints_with_input)
    return pred * (scale / normalize_2d(seq.points_2d, seq.visibility)[1])[:, None, None]


def c3dpo_test_predictions(model, split: Split, unit: float, inputs: str) -> Predictions:
    """C3DPO's test predictions in PRN's per-frame units; with the authors' ``"hip"`` inputs, ``millimetres`` as
    the authors scale them back: each frame times the ground truth's hip distance (:func:`hip_frame`) (the others: the PRN
    protocol's, :func:`benchmarks.registry.millimetres`)."""
    from prn.data import normalize_2d

    out = Predictions()
    mm = []
    for seq, truth in zip(split.test_inputs, split.test_truth):
        pred, scale = _c3dpo_shapes(model, seq, unit, inputs)
        out.append(pred * (scale / normalize_2d(seq.points_2d, seq.visibility)[1])[:, None, None])
        mm.append(pred * hip_frame(truth.points_3d, np.ones(truth.points_3d.shape[:2]), root_joint(truth))[1]
                  [:, None, None])
    if inputs == "hip":
        out.millimetres = mm
    return out


@register_method("C3DPO", ("gt-ortho", "gt-persp", "sh"), "C3DPO (Novotny et al., ICCV 2019), reimplemented")
def c3dpo(split: Split, ctx: RunContext) -> list[np.ndarray]:
    from baselines.c3dpo import PAPER_ITERATIONS, C3DPOConfig, load_c3dpo, train_c3dpo
    from nrsfm.metrics import mpjpe_prn

    unit = c3dpo_unit(split.train_inputs, ctx.c3dpo_inputs)
    truth_mm = np.concatenate([t.points_3d for t in split.test_truth])

    def test_error(model):  # a diagnostic along training (--c3dpo-monitor); nothing is chosen with it
        preds = c3dpo_test_predictions(model, split, unit, ctx.c3dpo_inputs)
        return {"test_mpjpe_mm": mpjpe_prn(np.concatenate(millimetres(preds, split.test_truth)), truth_mm)}

    inputs, weights, _ = c3dpo_inputs(split.train_inputs, unit, ctx.c3dpo_inputs)
    # the authors' 90 epochs, scaled as PRN's 70k iterations are, unless given
    iterations = ctx.c3dpo_iterations or max(1, round(ctx.iterations * PAPER_ITERATIONS / 70_000))
    config = C3DPOConfig(iterations=iterations, batch=ctx.c3dpo_batch, keypoint_rescale=ctx.c3dpo_rescale,
                         optimizer=ctx.c3dpo_optimizer, lr=ctx.c3dpo_lr, precision=ctx.c3dpo_precision,
                         repeat=ctx.c3dpo_repeat, seed=ctx.seed, device=ctx.device,
                         checkpoint_every=max(100, iterations // 20))
    cache = ctx.cache_dir("C3DPO", {"config": config.key(), "data": split.tag, "input": split.input_type,
                                    "inputs": ctx.c3dpo_inputs})
    key = f"C3DPO ({split.input_type})"
    if (cache / "model.pt").exists() and not ctx.retrain:
        model = load_c3dpo(cache / "model.pt", ctx.device)
        info = json.loads((cache / "train.json").read_text())
        ctx.timings[key] = {"cached": True, "train_seconds": info["seconds"], "iterations": iterations,
                            "cache": str(cache)}
    else:
        model, info = train_c3dpo(inputs, weights, config, cache, resume=not ctx.retrain, progress=ctx.progress,
                                  monitor=test_error if ctx.c3dpo_monitor else None,
                                  cuda_graph=None if ctx.c3dpo_cuda_graph else False, compile=ctx.c3dpo_compile)
        ctx.timings[key] = {"cached": False, "train_seconds": info["seconds"], "iterations": iterations,
                            "cache": str(cache)}
    if info.get("monitor"):
        ctx.timings[key]["monitor"] = info["monitor"]
    return c3dpo_test_predictions(model, split, unit, ctx.c3dpo_inputs)


def methods() -> dict[str, Method]:
    """Every registered row, the built-in ones above included."""
    return registered()


def get_method(name: str) -> Method:
    """The registered row ``name``."""
    m = methods()
    if name not in m:
        raise ValidationError(f"method: expected one of {list(m)}, got {name!r}")
    return m[name]
