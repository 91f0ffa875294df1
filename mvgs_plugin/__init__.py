"""MVGS controller: backend-agnostic multi-view regulated training for Gaussian splatting."""
