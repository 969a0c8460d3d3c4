"""Contracts every registered solver keeps: finite output or a clear error on degenerate input, and results
that do not depend on the units or the name of the tracks."""

import numpy as np
import pytest

from nrsfm import SolverError, solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.metrics import e3d
from nrsfm.sequence import Sequence
from nrsfm.solvers import available_solvers, get_solver


def _degenerate(case: str) -> Sequence:
    rng = np.random.default_rng(0)
    if case == "rigid":
        return lowrank_sequence(12, 9, 1, seed=4)
    if case == "planar":
        shape = np.c_[rng.standard_normal((10, 2)), np.zeros(10)]
        pts = np.einsum("fij,pj->fpi", lowrank_sequence(10, 10, 1, seed=0).camera_rotations, shape)
        return Sequence(points_2d=pts[..., :2], points_3d=pts)
    if case == "three_frames":  # 6 rows: a rank-3K factorisation with K = 2 fits W exactly
        return lowrank_sequence(3, 10, 2, seed=0)
    if case == "three_frames_four_points":  # EM-PND's factorisation start raised numpy's LinAlgError here
        return lowrank_sequence(3, 4, 2, seed=304)
    if case == "static_camera":  # one frame repeated: no 3D information at all
        return Sequence(points_2d=np.repeat(lowrank_sequence(10, 10, 1, seed=0).points_2d[:1], 10, axis=0))
    if case == "collinear":  # one line in every frame, scaled at random (EM-PND raised torch's LinAlgError)
        line = np.c_[np.linspace(0, 1, 8), np.linspace(0, 2, 8)]
        return Sequence(points_2d=line[None] * np.random.default_rng(1).random((10, 1, 1)))
    if case == "coincident":  # every frame's points at one place (CSF2 and EM-PPCA raised numpy's ValueError)
        return Sequence(points_2d=np.repeat(rng.standard_normal((10, 1, 2)), 8, axis=1))
    vis = np.ones((30, 12))
    if case == "point_never_visible":
        vis[:, 4] = 0
    else:
        vis[5] = 0  # "frame_all_missing"
    return lowrank_sequence(30, 12, 2, seed=0).replace(visibility=vis)


@pytest.mark.parametrize("case", ["rigid", "planar", "three_frames", "three_frames_four_points", "static_camera",
                                  "collinear", "coincident", "frame_all_missing", "point_never_visible"])
def test_every_solver_gives_finite_shapes_or_a_clear_error_on_degenerate_input(case):
    """The issue's degenerate inputs, for every registered solver: finite shapes and cameras, or an NRSfMError
    whose message names the solver (never NaN, never a bare error from a library underneath); a rigid sequence
    is always solved."""
    from nrsfm.errors import NRSfMError

    seq = _degenerate(case)
    for name in available_solvers():
        try:
            rec = solve(seq, name)
        except NRSfMError as err:
            assert case != "rigid", f"{name} refused a rigid sequence: {err}"
            assert str(err).startswith(f"{name}:"), (name, str(err))
            continue
        assert rec.points_3d.shape == (seq.n_frames, seq.n_points, 3), name
        assert np.isfinite(rec.points_3d).all() and np.isfinite(rec.rotations).all(), name
        if case in ("coincident", "frame_all_missing", "point_never_visible"):
            raise AssertionError(f"{name} solved a sequence with {case.replace('_', ' ')}")


def test_every_solver_refuses_tracks_without_extent():
    """Every frame's visible points at one place (here also with points missing): one shared message."""
    from nrsfm.solvers import get_solver

    complete = _degenerate("coincident")
    missing = complete.replace(points_2d=np.where(np.arange(8)[None, :, None] == 3, np.nan, complete.points_2d),
                               visibility=np.arange(8)[None].repeat(10, 0) != 3)
    for name in available_solvers():
        for seq in (complete, missing) if get_solver(name).handles_missing else (complete,):
            with pytest.raises(SolverError, match=rf"^{name}: the visible points of every frame of .* coincide"):
                solve(seq, name)


def test_solvers_of_orthographic_tracks_refuse_perspective_ones_with_the_fix():
    from nrsfm.datasets.synthetic import human_sequences
    from nrsfm.solvers import get_solver

    seq = human_sequences(("S9",), ("turning",), (1,), n_frames=30, projection="perspective")[0]
    for name in available_solvers():
        if get_solver(name).handles_perspective:
            assert np.isfinite(solve(seq, name).points_3d).all(), name
            continue
        with pytest.raises(SolverError, match=rf"^{name}: expected orthographic tracks, got perspective .*"
                                              r"seq\.to_weak_perspective\(\)"):
            solve(seq, name)
        assert np.isfinite(solve(seq.to_weak_perspective(), name).points_3d).all(), name


def test_a_point_never_visible_is_refused_with_the_fix():
    seq = _degenerate("point_never_visible")
    with pytest.raises(SolverError, match=r"point 4 is visible in no frame.*select_points"):
        solve(seq, "csf2")
    kept = seq.select_points(seq.visibility.any(axis=0))
    assert kept.n_points == 11 and np.isfinite(solve(kept, "csf2").points_3d).all()


def test_every_solver_refuses_two_frames():
    """Two orthographic views leave even a rigid shape's depths free (a rotation about one axis): every solver
    returned e3D .27-8.5 on a rigid 2 x 15 sequence before, against .0000 from three frames."""
    seq = lowrank_sequence(2, 15, 1, seed=1)
    for name in available_solvers():
        with pytest.raises(SolverError, match=rf"^{name}: expected at least 3 frames, got 2"):
            solve(seq, name)
        assert e3d(solve(lowrank_sequence(3, 15, 1, seed=1), name).points_3d,
                   lowrank_sequence(3, 15, 1, seed=1).points_3d) < 1e-3, name


def test_every_solver_refuses_three_points():
    """A triangle is planar: rank3, CSF2, SPM and EM-PPCA returned shapes with e3D .9-5.5 before."""
    seq = lowrank_sequence(20, 3, 1, seed=1)
    for name in available_solvers():
        with pytest.raises(SolverError, match=rf"^{name}: expected at least 4 points, got 3"):
            solve(seq, name)


@pytest.mark.parametrize("name", ["rank3", "csf2", "spm", "pr", "empnd", "emppca", "consensus"])
def test_solvers_do_not_depend_on_the_units_of_the_tracks(name):
    """The same noise-free sequence in units 1e5 and 1e-7 times smaller or larger: the same e3D (CSF2 gave .98
    at 1e5 and EM-PPCA, which starts from it, .86, against .044 and .0000 at 1, before its tracks were
    normalised)."""
    seq = lowrank_sequence(40, 15, 2, seed=1)
    errors = []
    for scale in (1.0, 1e5, 1e-7):
        scaled = seq.replace(points_2d=seq.points_2d * scale, points_3d=seq.points_3d * scale)
        errors.append(e3d(solve(scaled, name).points_3d, scaled.points_3d))
    assert max(errors) - min(errors) < 1e-3, errors


@pytest.mark.parametrize("name", ["rank3", "csf2", "spm", "pr", "empnd", "emppca", "consensus"])
def test_solvers_do_not_depend_on_the_name_of_the_file(name, tmp_path):
    """The same tracks saved as ``face.mat``, ``drink.mat`` and ``x.mat`` give the same shapes: no setting is
    looked up by a sequence's name."""
    from scipy.io import savemat

    from nrsfm.datasets import load_sequence

    seq = lowrank_sequence(30, 12, 2, seed=4, noise=0.01)
    shapes = []
    for stem in ("face", "drink", "x"):
        path = tmp_path / f"{stem}.mat"
        savemat(path, {"X": seq.points_3d.transpose(2, 1, 0)})  # the PND layout, 3 x P x F
        loaded = load_sequence(path)
        assert loaded.name == stem
        shapes.append(solve(loaded, name).points_3d)
    # equal to the convex solvers' tolerance (SPM's programs agree to 1e-8 from one run to the next)
    np.testing.assert_allclose(shapes[1], shapes[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(shapes[2], shapes[0], rtol=0, atol=1e-6)
