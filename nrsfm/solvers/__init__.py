"""NRSfM solvers behind one registry.

>>> from nrsfm.solvers import get_solver
>>> spec = get_solver("rank3")
>>> rec = spec.solve(seq, spec.params())  # doctest: +SKIP
"""

import dataclasses

from nrsfm.errors import ValidationError
from nrsfm.solvers.base import (Reconstruction, SolverSpec, available_solvers, check_param_values, get_solver,
                                params_from_strings, register)
from nrsfm.solvers import rank3 as _rank3  # noqa: F401  (registers "rank3")
from nrsfm.solvers.rank3 import Rank3Params, solve_rank3
from nrsfm.solvers.pr import PRParams, solve_pr
from nrsfm.solvers.csf2 import CSF2Params, solve_csf2
from nrsfm.solvers.spm import SPMParams, solve_spm
from nrsfm.solvers.empnd import EMPNDParams, solve_empnd
from nrsfm.solvers.emppca import EMPPCAParams, solve_emppca
from nrsfm.solvers.consensus import ConsensusParams, average_reconstructions, solve_consensus


def solve(seq, method: str = "rank3", params=None, **overrides) -> Reconstruction:
    """Solve ``seq`` with the registered ``method``; keyword overrides build its params (or replace fields of
    ``params`` when both are given)."""
    spec = get_solver(method)
    check_param_values(spec.params, overrides, method)
    if params is None:
        params = spec.params(**overrides)
    elif overrides:  # a params object and keyword overrides: the overrides win
        if not isinstance(params, spec.params):
            raise ValidationError(f"params: expected {spec.params.__name__}, got {type(params).__name__}")
        params = dataclasses.replace(params, **overrides)
    return spec.solve(seq, params)


__all__ = ["Reconstruction", "SolverSpec", "available_solvers", "get_solver", "params_from_strings", "register",
           "solve", "Rank3Params", "solve_rank3", "PRParams", "solve_pr", "CSF2Params", "solve_csf2", "SPMParams",
           "solve_spm", "EMPNDParams", "solve_empnd",
           "EMPPCAParams", "solve_emppca", "ConsensusParams", "average_reconstructions", "solve_consensus"]
