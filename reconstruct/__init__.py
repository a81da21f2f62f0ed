"""Reconstruction stage: pycolmap SfM with GNSS priors, alignment, dense depth + fusion, proxy mesh."""
