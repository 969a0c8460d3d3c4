"""NRSfM solvers behind one registry (:mod:`nrsfm.solvers.registry`).

>>> from nrsfm.solvers import get_solver
>>> spec = get_solver("rank3")
>>> rec = spec.solve(seq, spec.params())  # doctest: +SKIP

Importing this package registers every solver.
"""

from nrsfm.reconstruction import Reconstruction
from nrsfm.solvers.registry import (SolverSpec, available_solvers, get_solver, params_from_strings, register,
                                    solve)
from nrsfm.solvers.rank3 import Rank3Params, solve_rank3
from nrsfm.solvers.pr import PRParams, solve_pr
from nrsfm.solvers.csf2 import CSF2Params, solve_csf2
from nrsfm.solvers.spm import SPMParams, solve_spm
from nrsfm.solvers.empnd import EMPNDParams, solve_empnd
from nrsfm.solvers.emppca import EMPPCAParams, solve_emppca
from nrsfm.solvers.consensus import ConsensusParams, average_reconstructions, solve_consensus

__all__ = ["Reconstruction", "SolverSpec", "available_solvers", "get_solver", "params_from_strings", "register",
           "solve", "Rank3Params", "solve_rank3", "PRParams", "solve_pr", "CSF2Params", "solve_csf2", "SPMParams",
           "solve_spm", "EMPNDParams", "solve_empnd",
           "EMPPCAParams", "solve_emppca", "ConsensusParams", "average_reconstructions", "solve_consensus"]
