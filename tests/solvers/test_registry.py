"""The solver registry: lookup, parameter coercion and checks."""

import numpy as np
import pytest

from nrsfm import ValidationError, solve
from nrsfm.datasets.synthetic import lowrank_sequence
from nrsfm.solvers import Rank3Params, available_solvers, get_solver, params_from_strings


def test_registry_lists_and_rejects():
    assert "rank3" in available_solvers()
    with pytest.raises(ValidationError, match=r"method: expected one of .*'rank3'.*got 'nope'"):
        get_solver("nope")


def test_params_from_strings_coerces_and_validates():
    assert params_from_strings(Rank3Params, ["min_eigenvalue=1e-6"]).min_eigenvalue == 1e-6
    with pytest.raises(ValidationError, match="no parameter 'K'"):
        params_from_strings(Rank3Params, ["K=3"])
    with pytest.raises(ValidationError, match="expected float"):
        params_from_strings(Rank3Params, ["min_eigenvalue=abc"])
    with pytest.raises(ValidationError, match="NAME=VALUE"):
        params_from_strings(Rank3Params, ["min_eigenvalue"])
    with pytest.raises(ValidationError, match=r"min_eigenvalue: expected a value in \(0, 1\)"):
        Rank3Params(min_eigenvalue=2.0)
    seq = lowrank_sequence(10, 6, 1)
    for name in ("csf2", "pr", "empnd"):  # NaN passes every per-class check ("tol >= 0" is false for it)
        with pytest.raises(ValidationError, match=rf"{get_solver(name).params.__name__}.tol: expected a finite"):
            solve(seq, name, params_from_strings(get_solver(name).params, ["tol=nan"]))


def test_solve_checks_keyword_parameters_before_building_them():
    from nrsfm.solvers import CSF2Params

    seq = lowrank_sequence(30, 10, 2, seed=1)
    for value, got in (("12", "str '12'"), (2.5, "float 2.5"), (True, "bool True")):  # raised TypeError inside
        with pytest.raises(ValidationError, match=f"CSF2Params.K: expected int, got {got}"):
            solve(seq, "csf2", K=value)
    with pytest.raises(ValidationError, match="CSF2Params has no parameter 'KK'; known: \\['K', "):
        solve(seq, "csf2", KK=3)
    assert solve(seq, "csf2", K=np.int64(2), tol=0).params["K"] == 2  # numpy integers, and ints for floats
    # a params object and keywords: the keywords replace its fields (they were silently ignored)
    assert solve(seq, "csf2", CSF2Params(d=5), K=2).params == {**vars(CSF2Params(d=5)), "K": 2}
    with pytest.raises(ValidationError, match="params: expected CSF2Params, got Rank3Params"):
        solve(seq, "csf2", Rank3Params(), K=2)


def test_large_arrays_on_heap_is_scoped_and_harmless():
    import platform

    from nrsfm._malloc import large_arrays_on_heap

    with large_arrays_on_heap() as ok:
        big = np.ones(40 << 17)  # 40 MiB, above glibc's default mmap threshold
        assert big.sum() == big.size
    assert ok == (platform.system() == "Linux" and platform.libc_ver()[0] == "glibc")
