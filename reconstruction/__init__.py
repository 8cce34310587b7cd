"""Reconstruction: spectral images from single Bayer raw images (thesis ch. 3).

Contents
--------
:mod:`reconstruction.operators`
    M, Ω, Φ, B and the priors' difference operators, each with adjoint and dot test.
:class:`LatentSpace`, :class:`ImageFormation`, :func:`build_formation`
    A = M·Ω·Φ·B (3.1) or its direct-colour form (3.27), per patch.
:data:`PRIORS`, :class:`PriorTerm`
    The prior combinations of Table 3.1.
:class:`Problem`
    One patch's problem: data, A, priors, weights, non-negativity.
:mod:`reconstruction.solvers`
    ADMM with the exact FFT quadratic step and preconditioned CG (§3.7).
:func:`select_weights`
    Algorithm 3 with the MDC, MSE and demosaicing criteria (§3.6).
:func:`reconstruct_patches`
    The patch-wise Dask driver that skips negligible dispersion and flat patches (§3.8.1).
:func:`reconstruct`
    The whole job: validation, normalisation, weights, patches, outputs and a log.
"""

from reconstruction.image_formation import ImageFormation, LatentSpace, build_formation
from reconstruction.patches import PatchOptions, SolverOptions, reconstruct_patches
from reconstruction.prior_terms import PRIORS, PriorTerm, prior_terms
from reconstruction.problem import Problem
from reconstruction.reconstruct import Reconstruction, reconstruct
from reconstruction.weights import CRITERIA, WeightSelection, select_weights

__all__ = [
    "CRITERIA",
    "PRIORS",
    "ImageFormation",
    "LatentSpace",
    "PatchOptions",
    "PriorTerm",
    "Problem",
    "Reconstruction",
    "SolverOptions",
    "WeightSelection",
    "build_formation",
    "prior_terms",
    "reconstruct",
    "reconstruct_patches",
    "select_weights",
]
