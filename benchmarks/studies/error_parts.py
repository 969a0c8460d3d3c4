"""Where a Table 1 row's 3D error lies: the orientation of each frame's shape, or the shape itself.

    python -m benchmarks.studies.error_parts [the options of benchmarks.table1]

Runs the rows of :mod:`benchmarks.table1` (default ``PRN-FCN,GT 3D,C3DPO``) with the same options, so that the
models it cached are read back, and splits each row's test error, per frame, under PRN's protocol (shapes centred
on the joints' mean, depth sign chosen per frame, millimetres):

- **MPJPE**, the table's number, and the mean distance of its image coordinates and of its depths alone
  (a row that keeps the input's image coordinates, as C3DPO does, errs in depth only);
- **after rotation**: the MPJPE once the prediction is turned by the proper rotation that fits it best to the
  ground truth (orthogonal Procrustes, no scale): what is left is the error of the shape itself;
- the **angle** of that rotation (median over frames) and its mean absolute components about the image axes:
  pitch (about the image's horizontal axis), yaw (its vertical axis) and roll (the optical axis); with GT-ortho
  input the image coordinates are exact, so a row's orientation error is a depth error that a rotation out of
  the image plane explains;
- **PA-MPJPE**: after a rotation and a scale (:func:`nrsfm.metrics.pa_mpjpe`), the depth sign chosen first.

Two rows with the same MPJPE after rotation differ only in how they orient the shapes they predict. The table
(``error_parts.md``) and, per action, the JSON (``error_parts.json``) are written into the table's ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict

import numpy as np

from benchmarks.common import markdown_table, run_metadata, run_table, write_json

#: The columns of the output table (after the row and input).
COLUMNS = ("frames", "MPJPE (mm)", "mean |xy| / |depth| error (mm)", "after rotation (mm)", "orientation share",
           "median angle (deg)", "mean |pitch| / |yaw| / |roll| (deg)", "PA-MPJPE (mm)")


def error_parts_per_frame(pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:
    """Per frame of `(F, P, 3)` predictions and ground truth (mm): ``mpjpe``, ``xy`` and ``depth`` (the mean
    distance of the image coordinates and of the depths alone), ``rotated`` (after the best proper rotation),
    ``angle`` (its angle, degrees), ``axes`` `(F, 3)` (its rotation vector about the image x, y and optical axes,
    degrees) and ``pa_mpjpe``, all `(F,)` but ``axes``."""
    from scipy.spatial.transform import Rotation

    from nrsfm.geometry import nearest_rotation
    from nrsfm.metrics import pa_mpjpe_per_frame, prn_frames

    p, g = prn_frames(pred, gt)  # centred, the depth sign chosen per frame
    rot = nearest_rotation(np.einsum("fpi,fpj->fij", p, g))  # p @ rot ~ g, det +1
    rotated = np.linalg.norm(p @ rot - g, axis=2).mean(axis=1)
    axes = np.degrees(Rotation.from_matrix(np.swapaxes(rot, 1, 2)).as_rotvec())  # acting on column vectors
    return {"mpjpe": np.linalg.norm(p - g, axis=2).mean(axis=1),
            "xy": np.linalg.norm(p[..., :2] - g[..., :2], axis=2).mean(axis=1),
            "depth": np.abs(p[..., 2] - g[..., 2]).mean(axis=1), "rotated": rotated,
            "angle": np.linalg.norm(axes, axis=1), "axes": axes,
            "pa_mpjpe": pa_mpjpe_per_frame(p, g)}


def summarise(parts: dict[str, np.ndarray]) -> list:
    """One table row (:data:`COLUMNS`) of :func:`error_parts_per_frame`'s output."""
    mpjpe, rotated = float(parts["mpjpe"].mean()), float(parts["rotated"].mean())
    pitch, yaw, roll = np.abs(parts["axes"]).mean(axis=0)
    return [len(parts["mpjpe"]), mpjpe, f"{parts['xy'].mean():.1f} / {parts['depth'].mean():.1f}", rotated,
            f"{(mpjpe - rotated) / mpjpe:.0%}" if mpjpe > 0 else "-",
            float(np.median(parts["angle"])), f"{pitch:.1f} / {yaw:.1f} / {roll:.1f}", float(parts["pa_mpjpe"].mean())]


def main(argv: list[str] | None = None) -> int:
    from benchmarks import table1

    p = table1.parser("python -m benchmarks.studies.error_parts", __doc__.split("\n\n")[0])
    p.set_defaults(methods="PRN-FCN,GT 3D,C3DPO")
    args = table1.parse_args(p, argv)
    return run_table("error_parts", _run, args)


def _run(args: argparse.Namespace) -> int:
    from benchmarks import table1
    from benchmarks.registry import millimetres

    rows = table1.run_rows(args, keep_predictions=True)
    table, per_action = [], {}
    for (name, inp), preds in rows.predictions.items():
        split = rows.splits[inp]
        frames: dict[str, list[dict]] = defaultdict(list)
        for pred, truth in zip(millimetres(preds, split.test_truth), split.test_truth):
            parts = error_parts_per_frame(pred, truth.points_3d)
            frames[truth.meta.get("action", "all")].append(parts)
        joined = {a: {k: np.concatenate([f[k] for f in v]) for k in v[0]} for a, v in frames.items()}
        every = {k: np.concatenate([v[k] for v in joined.values()]) for k in next(iter(joined.values()))}
        table.append([name, inp, *summarise(every)])
        per_action[f"{name} ({inp})"] = {a: dict(zip(COLUMNS, summarise(v))) for a, v in sorted(joined.items())}
    text = markdown_table(["row", "input", *COLUMNS], table)
    print(text)
    out = rows.ctx.out_dir
    (out / "error_parts.md").write_text(text + "\n")
    write_json(out / "error_parts.json", {"meta": run_metadata(study="error_parts", data=rows.desc,
                                                               methods=rows.names, iterations=rows.ctx.iterations,
                                                               timings=rows.ctx.timings),
                                          "rows": [dict(zip(["row", "input", *COLUMNS], r)) for r in table],
                                          "per_action": per_action})
    print(f"\nwrote {out}/error_parts.md, error_parts.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
