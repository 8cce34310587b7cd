"""Reconstruction: operators, priors, ADMM solvers and the patch-wise driver (thesis ch. 3).

Built in later issues; this package is part of the labkit distribution from the start.
"""
