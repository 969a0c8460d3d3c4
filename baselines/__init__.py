"""Baselines of the PRN paper: networks trained on pseudo-3D labels of classical solvers ("+NN"), on ground-truth
3D, and C3DPO."""
