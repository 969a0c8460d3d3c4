"""nrsfm: non-rigid structure from motion and learned 3D structure from 2D annotations.

Quick use::

    import nrsfm
    seq = nrsfm.load_sequence("drink.mat")          # or .npz; -> Sequence
    rec = nrsfm.solve(seq, "rank3")                 # -> Reconstruction
    nrsfm.metrics.e3d(rec.points_3d, seq.points_3d)
"""

from nrsfm import metrics
from nrsfm.errors import DataFormatError, NRSfMError, SolverError, ValidationError
from nrsfm.datasets.files import load_sequence
from nrsfm.reconstruction import Reconstruction
from nrsfm.sequence import Sequence
from nrsfm.solvers import available_solvers, get_solver, solve

__version__ = "0.1.0"
__all__ = ["Sequence", "Reconstruction", "load_sequence", "solve", "get_solver", "available_solvers", "metrics",
           "NRSfMError", "ValidationError", "DataFormatError", "SolverError", "__version__"]
