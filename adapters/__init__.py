"""Adapters: one module per Gaussian model family (3DGS, Scaffold-GS, 4DGS)."""
