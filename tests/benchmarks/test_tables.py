"""The tables beyond Table 1: Table 2 and supplementary Table S2 (images), supplementary Table S1 (missing points),
Table 3 (faces), Table 4 (dense bodies)."""

import argparse
import dataclasses
import json
import sys

import numpy as np
import pytest

from benchmarks import harness, table1, table2, table3, table4, table_s1, table_s2
from benchmarks.registry import Split
from nrsfm.datasets.synthetic import face_sequences, surface_sequence


def test_table_s1_trains_one_model_per_ratio_and_variant_and_drops_test_points(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(table1, "SYNTHETIC_FRAMES", 40)
    monkeypatch.setattr(table1, "SYNTHETIC_MOTIONS", ("walking", "waving", "bending", "turning"))  # 160 frames
    out = tmp_path / "s1"
    assert table_s1.main(["--iterations", "12", "--ratios", "0,0.2", "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("table_s1: the embedded synthetic stand-in")
    assert "| PRN-FCN (ours) |" in text and "| 0% | 20% |" in text and "(paper)" not in text  # synthetic: no paper
    assert "| PRN-FCN (ours; normalised with the hidden points, as a preprocessed dataset would be) |" in text
    assert "lr x0.8 every 5,000 iterations (the paper's)" in text
    data = json.loads((out / "table_s1.json").read_text())
    avg = {(r["variant"], r["missing_ratio"]): r["per_action"]["Avg"]["mpjpe_mm"] for r in data["results"]}
    assert set(avg) == {(v, r) for v in ("visible", "hidden") for r in (0.0, 0.2)}
    assert all(np.isfinite(v) for v in avg.values())
    assert avg[("visible", 0.0)] == avg[("hidden", 0.0)]  # nothing missing: one model
    assert avg[("visible", 0.2)] != avg[("hidden", 0.2)]
    parts = {(r["variant"], r["missing_ratio"]): r["mpjpe_by_visibility_mm"] for r in data["results"]}
    assert parts[("visible", 0.0)]["missing"] is None
    assert parts[("visible", 0.0)]["visible"] == pytest.approx(avg[("visible", 0.0)])
    for v in ("visible", "hidden"):
        # about a fifth of the joints are missing: the average lies between the two parts, near 4:1
        p = parts[(v, 0.2)]
        lo, hi = sorted((p["visible"], p["missing"]))
        assert lo < avg[(v, 0.2)] < hi
        assert avg[(v, 0.2)] == pytest.approx(0.8 * p["visible"] + 0.2 * p["missing"], rel=0.05)
        assert np.isfinite(p["test_complete"]) and p["test_complete"] != pytest.approx(avg[(v, 0.2)])
    assert "| PRN-FCN, visible: missing joints | – |" in text
    assert parts[("visible", 0.0)]["visible_alone"] == pytest.approx(avg[("visible", 0.0)])
    assert parts[("visible", 0.0)]["test_complete"] == pytest.approx(avg[("visible", 0.0)])
    assert "| PRN-FCN, hidden: all joints, the test inputs complete (points missing in training only) |" in text
    caches = {t["cache"] for per in data["meta"]["timings"].values() for t in per.values()}
    assert len(caches) == 3 and len(list((out / "cache").iterdir())) == 3  # 0%, and 20% per variant
    assert (out / "table_s1.png").exists() and (out / "table_s1.csv").exists()
    assert table_s1.main(["--ratios", "0,1.5", "--out", str(out)]) == 2
    assert "--ratios: expected comma-separated fractions in [0, 1)" in capsys.readouterr().err
    assert table_s1.main(["--variants", "both", "--out", str(out)]) == 2
    assert "--variants: expected names among" in capsys.readouterr().err


def test_visible_alone_ignores_the_missing_joints():
    from nrsfm.metrics import mpjpe_prn_per_joint

    rng = np.random.default_rng(0)
    gt = rng.normal(size=(6, 17, 3)) * 100
    pred = gt + rng.normal(size=gt.shape) * 5
    pred[:3, :, 2] *= -1  # reflected frames: the z sign is chosen per frame
    vis = np.ones((6, 17), bool)
    np.testing.assert_allclose(table_s1._visible_alone(pred, gt, vis), mpjpe_prn_per_joint(pred, gt))
    vis[:, :4] = False
    bad = pred.copy()
    bad[:, :4] += 1000.0  # wild missing joints move neither the centring nor the z sign of the visible ones
    expected = table_s1._visible_alone(pred[:, 4:], gt[:, 4:], vis[:, 4:])
    np.testing.assert_allclose(table_s1._visible_alone(bad, gt, vis)[:, 4:], expected)
    assert (table_s1._visible_alone(bad, gt, vis)[:, 4:] < mpjpe_prn_per_joint(bad, gt)[:, 4:]).all()


def test_missing_split_marks_the_ratio_of_test_entries_missing():
    seqs = face_sequences(2, 200)
    split = table_s1.missing_split(Split(seqs, seqs, seqs, seqs, "gt-ortho"), 0.2)
    vis = np.concatenate([s.weights for s in split.test_inputs])
    assert abs((vis == 0).mean() - 0.2) < 0.02
    assert split.train_inputs[0].visibility is None  # training points drop per sample, in the trainer


def _tiny(spec, load):
    """``spec`` on ``load``'s tiny data: a narrow network, the table's point groups and alignment groups (of 16
    frames)."""
    keep = {k: v for k, v in spec.context.items() if k in ("point_groups", "groups")}
    if "groups" in keep:
        keep["group_size"] = 16
    return dataclasses.replace(spec, load=load, context={"width": 32, **keep}, synthetic_context=None)


def test_table3_computes_every_row_on_tiny_faces(tmp_path, capsys):
    def load(args):
        seqs = face_sequences(4, 24, seed=args.seed)
        return Split(seqs[:2], seqs[:2], seqs[2:], seqs[2:], "gt-ortho", sampling="random", tag="tiny-faces"), \
            {"data": "tiny faces"}

    spec = _tiny(table3.SPEC, load)
    args = harness.parser(spec).parse_args(["--iterations", "12", "--out", str(tmp_path), "--no-progress",
                                            "--jobs", "1", "--c3dpo-batch", "16", "--c3dpo-iterations", "6",
                                            "--direct", "rank3", "--plots", "--data", "synthetic"])
    assert harness.run(spec, args) == 0
    data = json.loads((tmp_path / "table3.json").read_text())
    errors = {r["method"]: r["error"] for r in data["results"]}
    assert set(errors) == set(table3.ROWS) | {"rank3 on the test data"} and not data["not_run"]
    assert table3.SPEC.direct == ("rank3", "pr", "empnd")
    assert all(0 < e < 2 for e in errors.values())
    for f in ("table3.png", "table3_qualitative.png", "table3_curves.png"):
        assert (tmp_path / f).stat().st_size > 5000, f
    text = capsys.readouterr().out
    assert "| PR + NN |" in text and "| EM-PND + NN |" in text and "Pseudo-labels" in text
    assert "| rank3 on the test data |" in text and "lr x0.8 every 5,000 iterations (the paper's)" in text
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["context"]["groups"] == 1 and table3.SPEC.context["group_size"] == 128  # faces: one alignment group


def _aflw_files(root, n: int, seed: int = 0):
    """AFLW2000-3D's release layout under ``root/aflw2000`` with ``n`` random faces."""
    rng = np.random.default_rng(seed)
    folder = root / "aflw2000"
    folder.mkdir(parents=True)
    x3 = rng.normal(size=(n, 3, 68)).astype(np.float32) * 20 + 100
    np.save(folder / "AFLW2000-3D.pts68.npy", x3)
    np.save(folder / "AFLW2000-3D-Reannotated.pts68.npy", x3[:, :2] + rng.normal(size=(n, 2, 68)).astype(np.float32))
    np.save(folder / "AFLW2000-3D.pose.npy", np.linspace(-100, 100, n).astype(np.float32))
    return x3


def test_table3_reads_aflw2000_in_two_sections_with_yaw_bands(tmp_path, capsys, monkeypatch):
    _aflw_files(tmp_path, 40)
    monkeypatch.setenv("NRSFM_DATA", str(tmp_path))
    monkeypatch.setattr(table3, "SPEC", dataclasses.replace(table3.SPEC, context={
        **table3.SPEC.context, "width": 32, "group_size": 12}))  # 30 training faces: groups of 12
    out = tmp_path / "o"
    assert table3.main(["--iterations", "6", "--c3dpo-iterations", "4", "--c3dpo-batch", "8", "--methods",
                        "PRN-FCN,C3DPO", "--direct", "rank3", "--out", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "#### fitted" in text and "#### reannotated" in text and "NE (paper, 300-VW)" in text
    data = json.loads((out / "table3.json").read_text())
    rows = {(r["section"], r["method"]): r for r in data["results"]}
    assert set(rows) == {(s, m) for s in ("fitted", "reannotated") for m in ("PRN-FCN", "C3DPO",
                                                                             "rank3 on the test data")}
    first = rows[("fitted", "PRN-FCN")]
    assert first["frames"] == 10 and first["paper_data"] == "300vw"  # the last 25% of 40 faces test
    assert sum(b["frames"] for b in first["bands"].values()) == 10 and set(first["bands"]) <= {"0-30", "30-60",
                                                                                                "60-90"}
    assert data["meta"]["data"]["first_test_face"] == 30
    timings = data["meta"]["timings"]  # one entry per row and section, none overwritten by the other section
    assert {"PRN-FCN (fitted)", "PRN-FCN (reannotated)", "C3DPO (fitted)", "C3DPO (reannotated)"} <= set(timings)
    # --validate: the first 80% of the 30 training faces train, the other 6 validate; no paper numbers
    assert table3.main(["--iterations", "6", "--methods", "GT 3D", "--direct", "", "--validate", "--out",
                        str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    data = json.loads((out / "table3.json").read_text())
    assert {r["frames"] for r in data["results"]} == {6} and data["meta"]["data"]["first_test_face"] == 24
    assert "validation faces" in text and "0.0441" not in text


def test_table2_computes_every_row_from_rendered_images(tmp_path, capsys, monkeypatch):
    pytest.importorskip("torchvision")
    monkeypatch.setattr(table1, "QUICK_FRAMES", 160)
    monkeypatch.setattr(table1, "QUICK_MOTIONS", ("walking",))
    monkeypatch.setattr(table1.h36m, "TRAIN_SUBJECTS", ("S1", "S5"))  # 160 frames, 40 label cuts a solver
    argv = ["--quick", "--iterations", "10", "--image-size", "32", "--out", str(tmp_path), "--no-progress",
            "--jobs", "1", "--labels-dir", str(tmp_path / "shared-labels")]
    assert table2.main(argv) == 0
    data = json.loads((tmp_path / "table2.json").read_text())
    assert {r["method"] for r in data["results"]} == set(table2.PAPER) and not data["not_run"]
    assert all(0 < r["error"] < 1000 for r in data["results"])
    assert data["meta"]["data"]["images"] == "rendered capsules, 32 px"
    text = capsys.readouterr().out
    assert "| PRN-CNN |" in text and "network: small" in text and "| spm | 20 | 0 |" not in text
    assert any((tmp_path / "shared-labels").iterdir())  # the pseudo-labels went where --labels-dir said
    assert len(list((tmp_path / "images").glob("*.npy"))) > 0  # the renders are cached
    assert table2.main(argv) == 0  # the second run reads everything back
    timings = json.loads((tmp_path / "meta.json").read_text())["timings"]
    assert all(t["cached"] for t in timings.values())


def test_image_tables_without_frames_are_a_clear_error(tmp_path, capsys):
    (tmp_path / "300vw-3d").mkdir()
    assert table_s2.main(["--root", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "table_s2: error:" in capsys.readouterr().err
    assert table2.main(["--image-size", "8", "--out", str(tmp_path / "o")]) == 2
    assert "--image-size: expected at least 16 pixels" in capsys.readouterr().err


def test_table3_and_table4_stand_ins_have_the_paper_layout():
    args = argparse.Namespace(data="synthetic", quick=True, seed=0, root=None)
    split, desc = table3.load(args)
    assert split.train_inputs[0].n_points == 68 and split.sampling == "random"
    assert {s.name for s in split.train_inputs}.isdisjoint(s.name for s in split.test_inputs)
    split, desc = table4.load(args)
    assert desc["points"] == 300 and split.sampling == "consecutive"
    assert table4.SPEC.context == {"width": 4096, "point_groups": 8}


def test_table4_trains_on_point_groups(tmp_path, capsys):
    def load(args):
        seqs = [surface_sequence(40, 8, 6, seed=i, name=f"t{i}") for i in range(3)]
        return Split(seqs[:2], seqs[:2], seqs[2:], seqs[2:], "gt-ortho", sampling="consecutive", tag="tiny"), \
            {"data": "tiny tubes"}

    spec = _tiny(table4.SPEC, load)
    args = harness.parser(spec).parse_args(["--iterations", "12", "--out", str(tmp_path), "--no-progress",
                                            "--methods", "PRN-FCN,PRN w/o reg", "--data", "synthetic"])
    assert harness.run(spec, args) == 0
    meta = json.loads((tmp_path / "meta.json").read_text())
    assert meta["context"] == {"width": 32, "point_groups": 8, "c3dpo_batch": 1024}
    assert "C3DPO (paper; not selected with --methods)" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [(["--iterations", "0"], "--iterations"),
                                           (["--methods", "nope"], "--methods: expected names")])
def test_tables_refuse_bad_arguments(tmp_path, capsys, argv, message):
    assert table3.main(argv + ["--out", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err


def test_table3_without_faces_is_a_clear_error(tmp_path, capsys):
    assert table3.main(["--root", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "--root: expected 300vw-3d or aflw2000 under" in capsys.readouterr().err
    assert table3.main(["--data", "300vw", "--root", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "300vw-3d: expected a dataset folder" in capsys.readouterr().err


def test_table1_plots_write_every_figure(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(table1, "SYNTHETIC_FRAMES", 40)
    assert table1.main(["--iterations", "12", "--out", str(tmp_path), "--no-progress", "--methods",
                        "PRN-FCN,GT 3D", "--plots"]) == 0
    for kind in ("actions", "qualitative", "curves"):
        assert (tmp_path / f"table1_gt-ortho_{kind}.png").stat().st_size > 5000, kind


def test_limb_colours_follow_the_joint_names():
    from benchmarks.figures import CENTRE, LEFT, RIGHT, limb_colours
    from nrsfm.datasets import h36m

    colours = dict(zip(h36m.EDGES, limb_colours(h36m.EDGES, h36m.JOINT_NAMES)))
    assert colours[(4, 5)] == LEFT and colours[(1, 2)] == RIGHT and colours[(7, 8)] == CENTRE
    assert colours[(0, 4)] == LEFT  # hip centre to the left hip: a left limb


def test_all_runs_the_chosen_tables_and_summarises(tmp_path, capsys, monkeypatch):
    from benchmarks import all as all_tables

    def fake_main(argv):  # a finished table3 folder, as the real harness writes it
        out = tmp_path / "o" / "table3"
        out.mkdir(parents=True)
        (out / "table3.json").write_text(json.dumps({"meta": {"data": {"data": "synthetic faces"}}, "paper": {},
                                                     "results": [{"section": "", "method": "PRN-FCN", "error": 0.2,
                                                                  "frames": 9, "paper": None},
                                                                 {"section": "", "method": "PRN w/o reg",
                                                                  "error": 0.4, "frames": 9, "paper": None}]}))
        assert "--quick" in argv and "--plots" in argv
        return 0

    monkeypatch.setattr(table3, "main", fake_main)
    assert all_tables.main(["--quick", "--tables", "table3", "--out", str(tmp_path / "o")]) == 0
    text = (tmp_path / "o" / "summary.md").read_text()
    assert "PRN beats PRN w/o reg: yes" in text and "| PRN-FCN | 0.2000 |" in text
    assert all_tables.main(["--tables", "nope"]) == 2


def test_all_runs_tables_side_by_side_in_one_thread_processes(tmp_path, monkeypatch):
    from benchmarks import all as all_tables

    script = """
import json, os, sys
from pathlib import Path
argv = sys.argv[1:]
name, out = argv[0], Path(argv[argv.index("--out") + 1])
out.mkdir(parents=True, exist_ok=True)
print("printed by", name)
if name == "table4":
    sys.exit(3)
error = 0.2 if os.environ["OMP_NUM_THREADS"] == "1" else 9.0  # a table must run on one thread
(out / (name + ".json")).write_text(json.dumps({"results": [
    {"section": "", "method": "PRN-FCN", "error": error, "frames": 9, "paper": None},
    {"section": "", "method": "PRN w/o reg", "error": 0.4, "frames": 9, "paper": None}]}))
"""
    monkeypatch.setattr(all_tables, "_command", lambda name, argv: [sys.executable, "-c", script, name, *argv])
    out = tmp_path / "o"
    assert all_tables.main(["--quick", "--tables", "table3,table_s2,table4", "--jobs", "2", "--out", str(out)]) == 1
    text = (out / "summary.md").read_text()
    assert text.index("### table3") < text.index("### table_s2") < text.index("### table4")  # in the asked order
    assert text.count("| PRN-FCN | 0.2000 |") == 2 and "PRN beats PRN w/o reg: yes" in text
    assert "table4 (stand-in" in text and "exit 3" in text
    assert (out / "table3" / "output.txt").read_text() == "printed by table3\n"
    assert all_tables.main(["--tables", "table3", "--jobs", "0"]) == 2


@pytest.mark.parametrize("argv, message", [(["--c3dpo-lr", "0"], "--c3dpo-lr"),
                                           (["--c3dpo-batch", "1"], "--c3dpo-batch"),
                                           (["--c3dpo-repeat", "0"], "--c3dpo-repeat")])
def test_table1_refuses_bad_c3dpo_settings(tmp_path, capsys, argv, message):
    assert table1.main(argv + ["--quick", "--out", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err
