"""Dataset loaders and synthetic generators, all returning :class:`~nrsfm.sequence.Sequence`.

Real data is found through an explicit ``root`` argument or the ``NRSFM_DATA``
environment variable (:func:`data_root`); nothing is downloaded or shipped.
"""

from nrsfm.datasets.paths import data_root, find_dataset
from nrsfm.datasets.cmu import CMU_SEQUENCES, list_cmu_sequences, load_cmu_mat
from nrsfm.datasets.files import load_sequence

__all__ = ["data_root", "find_dataset", "load_cmu_mat", "list_cmu_sequences", "CMU_SEQUENCES", "load_sequence"]
