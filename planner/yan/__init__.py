"""Yan et al. 2021's baseline (``yan.plan``)."""
