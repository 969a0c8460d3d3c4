"""Baselines of the PRN tables (+NN on NRSfM labels, C3DPO, GT-3D upper bound). Work in progress."""
