import json
import re

import numpy as np
import pytest

from nrsfm.cli import main
from nrsfm.datasets.synthetic import lowrank_sequence


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_solve_rigid_synthetic_json(tmp_path, capsys):
    path = lowrank_sequence(80, 20, 1, seed=3).save(tmp_path / "rigid.npz")
    code, out, err = _run(capsys, "solve", str(path), "--method", "rank3", "--json",
                          "--out", str(tmp_path / "rec.npz"), "--plot", str(tmp_path / "rec.png"))
    assert code == 0, err
    res = json.loads(out)
    for key in ("method", "frames", "points", "runtime_s", "metrics"):
        assert key in res
    assert res["frames"] == 80 and res["points"] == 20 and res["method"] == "rank3"
    assert set(res["metrics"]) >= {"e3d", "normalized_error", "mpjpe"}
    assert res["metrics"]["e3d"] < 1e-6
    assert (tmp_path / "rec.png").stat().st_size > 1000
    with np.load(tmp_path / "rec.npz", allow_pickle=False) as rec:
        assert rec["points_3d"].shape == (80, 20, 3)


def test_a_written_reconstruction_reads_back_and_info_summarises_it(tmp_path, capsys):
    from nrsfm import Reconstruction, load_sequence

    path = lowrank_sequence(40, 12, 2, seed=3).save(tmp_path / "seq.npz")
    code, out, err = _run(capsys, "solve", str(path), "-m", "csf2", "--set", "K=2", "--json",
                          "--out", str(tmp_path / "rec.npz"))
    assert code == 0, err
    rec = Reconstruction.load(tmp_path / "rec.npz")
    assert rec.method == "csf2" and rec.params["K"] == 2 and rec.points_3d.shape == (40, 12, 3)
    assert rec.rotations.shape == (40, 3, 3) and rec.iterations == json.loads(out)["iterations"]
    code, out, _ = _run(capsys, "info", str(tmp_path / "rec.npz"), "--json")
    info = json.loads(out)
    assert code == 0 and info["kind"] == "reconstruction" and info["frames"] == 40 and info["params"]["K"] == 2
    code, out, _ = _run(capsys, "info", str(tmp_path / "rec.npz"))
    assert code == 0 and "reconstruction by 'csf2'" in out and "K=2" in out
    # read as the other kind, each names the reader to use
    _one_line_error(*_run(capsys, "solve", str(tmp_path / "rec.npz"))[::2], "read it with nrsfm.Reconstruction.load")
    with pytest.raises(ValueError, match="it is a sequence: read it with nrsfm.load_sequence"):
        Reconstruction.load(path)
    assert load_sequence(path).n_frames == 40


def test_solve_text_output_and_set(tmp_path, capsys):
    path = lowrank_sequence(30, 10, 1, seed=3).save(tmp_path / "rigid.npz")
    code, out, _ = _run(capsys, "solve", str(path), "--set", "min_eigenvalue=1e-6")
    assert code == 0 and "e3D (camera frame)" in out and "normalised error" in out


def _one_line_error(code, err, pattern):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert pattern in lines[0], lines[0]


def test_bad_input_gives_one_line_and_exit_2(tmp_path, capsys):
    _one_line_error(*_run(capsys, "solve", str(tmp_path / "missing.npz"))[::2], "no such file")
    bad = tmp_path / "bad.npz"
    np.savez(bad, points_2d=np.zeros((2, 5, 17)))
    _one_line_error(*_run(capsys, "info", str(bad))[::2], "points_2d: expected (F, P, 2)")
    nan = tmp_path / "nan.npz"
    p2 = np.zeros((3, 4, 2))
    p2[1, 1, 0] = np.nan
    np.savez(nan, points_2d=p2)
    _one_line_error(*_run(capsys, "solve", str(nan))[::2], "NaN")
    good = lowrank_sequence(10, 6, 1).save(tmp_path / "good.npz")
    _one_line_error(*_run(capsys, "solve", str(good), "--method", "nope")[::2], "method: expected one of")
    _one_line_error(*_run(capsys, "solve", str(good), "--set", "K=2")[::2], "no parameter 'K'")
    _one_line_error(*_run(capsys, "frobnicate")[::2], "invalid choice")
    txt = tmp_path / "x.txt"
    txt.write_text("hello")
    _one_line_error(*_run(capsys, "info", str(txt))[::2], "expected a .npz sequence or a CMU NRSfM .mat")
    notzip = tmp_path / "notzip.npz"
    notzip.write_text("hello")
    _one_line_error(*_run(capsys, "info", str(notzip))[::2], "expected an .npz archive")
    missing = lowrank_sequence(10, 6, 1, missing=0.3, seed=2).save(tmp_path / "missing.npz")
    _one_line_error(*_run(capsys, "solve", str(missing))[::2], "expected complete tracks")
    _one_line_error(*_run(capsys, "solve", str(good), "--method", "empnd", "--set", "device=cuda:99")[::2],
                    "device: 'cuda:99' asked for, but torch sees")


def _savemat(path, **arrays):
    import scipy.io

    scipy.io.savemat(path, arrays)


MALFORMED = {
    "pickled.npz": (lambda p: np.savez(p, points_2d=np.array([np.zeros(3), np.zeros(2)], dtype=object)),
                    "got a pickled (object) array"),
    "text.npz": (lambda p: np.savez(p, points_2d=np.array(["a", "b"])), "points_2d: expected a numeric array"),
    "fps.npz": (lambda p: np.savez(p, points_2d=np.ones((4, 5, 2)), fps="fast"), "fps: expected a numeric array"),
    "complex.mat": (lambda p: _savemat(p, W=np.ones((8, 5)) + 1j), "W: expected real numbers, got complex"),
    "text.mat": (lambda p: _savemat(p, W="abc"), "W: expected a numeric array"),
    "scale.mat": (lambda p: _savemat(p, W=np.ones((8, 5)), scale=np.zeros((0, 0))), "scale: expected one number"),
    "pnd.mat": (lambda p: _savemat(p, X=np.ones((3, 5, 4)) * 1j), "X: expected real numbers"),
}


@pytest.mark.filterwarnings("error")  # numpy's ComplexWarning would have hidden a dropped imaginary part
@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_files_give_one_line_and_exit_2(tmp_path, capsys, name):
    write, pattern = MALFORMED[name]
    path = tmp_path / name
    write(path)
    for command in ("info", "solve"):
        _one_line_error(*_run(capsys, command, str(path))[::2], pattern)


def test_perspective_tracks_are_refused_with_the_fix_and_solved_as_weak_perspective(tmp_path, capsys):
    from nrsfm.datasets.synthetic import human_sequences

    seq = human_sequences(("S9",), ("turning",), (1,), n_frames=40, projection="perspective")[0]
    path = seq.save(tmp_path / "persp.npz")
    code, out, err = _run(capsys, "solve", str(path), "--method", "csf2")
    assert code == 2 and err.count("\n") == 1 and "--weak-perspective" in err and "(rank3)" in err
    code, out, err = _run(capsys, "solve", str(path), "--method", "csf2", "--weak-perspective", "--json")
    assert code == 0, err
    assert np.isfinite(json.loads(out)["metrics"]["e3d"])


def test_outputs_are_never_overwritten_without_force(tmp_path, capsys):
    good = lowrank_sequence(10, 6, 1).save(tmp_path / "good.npz")
    out = tmp_path / "rec.npz"
    out.write_bytes(b"user data")
    _one_line_error(*_run(capsys, "solve", str(good), "--out", str(out))[::2], "--force")
    assert out.read_bytes() == b"user data"
    code, _, err = _run(capsys, "solve", str(good), "--out", str(out), "--force")
    assert code == 0, err
    assert out.read_bytes() != b"user data"
    conv = tmp_path / "conv.npz"
    conv.write_bytes(b"mine")
    _one_line_error(*_run(capsys, "convert", str(good), str(conv))[::2], "--force")
    assert conv.read_bytes() == b"mine"
    # not even --force replaces the input file (here named another way)
    before = good.read_bytes()
    same = str(tmp_path / "." / "good.npz")
    for argv in (["solve", str(good), "--out", same, "--force"], ["convert", str(good), same, "--force"]):
        _one_line_error(*_run(capsys, *argv)[::2], "this is the input file")
    assert good.read_bytes() == before


def test_info_json_and_synth(tmp_path, capsys):
    for kind in ("rigid", "lowrank", "human", "face", "surface"):
        out = tmp_path / f"{kind}.npz"
        code, _, err = _run(capsys, "synth", kind, str(out), "--frames", "12")
        assert code == 0, err
        code, text, _ = _run(capsys, "info", str(out), "--json")
        info = json.loads(text)
        assert info["frames"] == 12 and info["ground_truth"] is True and info["valid"] is True


def test_solve_states_the_ks_the_automatic_k_passed_over(tmp_path, capsys, monkeypatch):
    from nrsfm.solvers import kselect

    path = lowrank_sequence(40, 12, 2, seed=3, noise=0.01).save(tmp_path / "seq.npz")
    calls = []

    def flips(shapes):  # K = 1, 2, 3 in turn: the third reverses its depth in half its frame pairs
        calls.append(shapes)
        return 0.5 if len(calls) == 3 else 0.0

    monkeypatch.setattr(kselect, "depth_flips", flips)
    code, out, err = _run(capsys, "solve", str(path), "-m", "csf2")
    assert code == 0, err
    assert re.search(r"K \(automatic\): +2 \(agreement rule\)", out)
    assert "Ks passed over:       3 (50.0%): depth reverses" in out and "(0.0% of frame pairs)" in out


def test_solve_states_the_automatic_k_and_its_rule(tmp_path, capsys):
    path = lowrank_sequence(40, 12, 2, seed=3, noise=0.01).save(tmp_path / "seq.npz")
    code, out, err = _run(capsys, "solve", str(path), "-m", "csf2")
    assert code == 0, err
    assert re.search(r"K \(automatic\): +[23] \(agreement rule\)", out)
    assert "Ks passed over" not in out
    code, out, _ = _run(capsys, "solve", str(path), "-m", "csf2", "--set", "k_rule=rank")
    assert "(rank rule)" in out
    code, out, _ = _run(capsys, "solve", str(path), "-m", "csf2", "--set", "K=3")
    assert code == 0 and "K (automatic)" not in out
    code, _, err = _run(capsys, "solve", str(path), "-m", "csf2", "--jobs", "0")
    assert code == 2 and "--jobs: expected a number of processes >= 1, got 0" in err


def test_methods_and_demo(tmp_path, capsys):
    code, out, _ = _run(capsys, "methods")
    assert code == 0 and "rank3" in out
    code, out, _ = _run(capsys, "methods", "csf2")  # one solver: its parameters for --set, with defaults and docs
    assert code == 0 and "--set NAME=VALUE" in out and "  K (int) = 0" in out and "residual_start (bool) = True" in out
    assert "K: number of basis shapes" in out and "spm " not in out
    _one_line_error(*_run(capsys, "methods", "nope")[::2], "method: expected one of")
    # the cells in two worker processes give the table of one process
    code, par, err = _run(capsys, "demo", "--out", str(tmp_path / "par"), "--methods", "rank3", "--jobs", "2")
    assert code == 0, err
    code, seq, err = _run(capsys, "demo", "--out", str(tmp_path / "demo"), "--methods", "rank3", "--jobs", "1")
    assert code == 0, err
    assert "| rigid | 200 x 30 | rank3 |" in seq
    assert any(p.suffix == ".png" for p in (tmp_path / "par").iterdir())

    def rows(text):  # the table without the time column
        return [r.split(" | ")[:5] for r in text.splitlines() if r.startswith("| ") and "rank3" in r]

    assert rows(par) == rows(seq) and len(rows(par)) == 4 and "(2 processes)" in par
    _one_line_error(*_run(capsys, "demo", "--jobs", "0")[::2], "--jobs: expected a number of processes >= 1")
    _one_line_error(*_run(capsys, "demo", "--out", str(tmp_path / "demo"))[::2], "not empty")
    _one_line_error(*_run(capsys, "demo", "--methods", "nope")[::2], "method: expected one of")


def test_a_demo_cell_reuses_the_reconstructions_handed_to_it(tmp_path, monkeypatch):
    from nrsfm import solve
    from nrsfm.cli import _demo_cell
    from nrsfm.solvers import starts

    seq = lowrank_sequence(40, 12, 2, seed=2, noise=0.01)
    alone = _demo_cell(seq, "consensus", tmp_path)
    monkeypatch.setattr(starts, "_SOLUTIONS", type(starts._SOLUTIONS)())  # a fresh worker process
    known = {name: solve(seq, name) for name in ("empnd", "pr")}  # the demo's first cells, from other processes
    handed = _demo_cell(seq, "consensus", tmp_path, known)
    assert alone["rec"].info["reused"] == [] and handed["rec"].info["reused"] == ["empnd", "pr"]
    np.testing.assert_allclose(handed["rec"].points_3d, alone["rec"].points_3d)
    assert handed["e3d"] == pytest.approx(alone["e3d"])


def test_console_script_entry_point():
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-m", "nrsfm.cli", "methods"], capture_output=True, text=True)
    assert res.returncode == 0 and "rank3" in res.stdout
    res = subprocess.run([sys.executable, "-m", "nrsfm.cli", "solve", "/nonexistent.npz"], capture_output=True,
                         text=True)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "Traceback" not in res.stderr


def test_threads_cap_the_pools_during_a_command_and_bad_counts_are_refused(tmp_path, capsys, monkeypatch):
    from threadpoolctl import threadpool_info

    import nrsfm.cli as cli

    path = lowrank_sequence(40, 12, 2, seed=1).save(tmp_path / "seq.npz")
    seen = {}

    def spy(args):  # what the command sees
        seen["blas"] = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
        return 0

    monkeypatch.setitem(cli._COMMANDS, "info", spy)
    assert _run(capsys, "--threads", "1", "info", str(path))[0] == 0
    assert seen["blas"] and max(seen["blas"]) == 1
    code, _, err = _run(capsys, "--threads", "-1", "info", str(path))
    assert code == 2 and "--threads" in err and len(err.strip().splitlines()) == 1
    code, out, _ = _run(capsys, "--threads", "0", "solve", str(path), "-m", "csf2", "--json")
    assert code == 0 and json.loads(out)["method"] == "csf2"
