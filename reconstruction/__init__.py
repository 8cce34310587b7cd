"""Reconstruction: spectral images from single Bayer raw images (thesis ch. 3).

The package is grouped by concern: :mod:`reconstruction.model` (what is solved: the
operators, the image formation, the priors, one patch's problem),
:mod:`reconstruction.solve` (how: the solvers, the weights' search, the patches) and
:mod:`reconstruction.evaluate` (how well: metrics, residual aberration, scoreboards). The
job sits at the top: :mod:`~reconstruction.options` and :mod:`~reconstruction.option_table`
(the options), :mod:`~reconstruction.choices` (every automatic choice, made once),
:mod:`~reconstruction.reconstruct` (the job) and :mod:`~reconstruction.result` (its
files), with :mod:`~reconstruction.baselines`, the demosaicing and warping methods that
the model, the weights and the evaluation all use.

Contents
--------
:mod:`reconstruction.model.operators`
    M, Ω, Φ, B and the priors' difference operators, each with adjoint and dot test.
:class:`LatentSpace`, :class:`ImageFormation`, :func:`build_formation`
    A = M·Ω·Φ·B (3.1) or its direct-colour form (3.27), per patch.
:data:`PRIORS`, :class:`PriorTerm`
    The prior combinations of Table 3.1.
:class:`Problem`
    One patch's problem: data, A, priors, weights, non-negativity.
:mod:`reconstruction.solve.solvers`
    ADMM with the exact FFT quadratic step and preconditioned CG (§3.7).
:func:`select_weights`
    Algorithm 3 with the MDC, MSE and demosaicing criteria (§3.6).
:func:`reconstruct_patches`
    The patch-wise Dask driver that skips negligible dispersion and flat patches (§3.8.1).
:class:`ReconstructOptions`, :func:`reconstruct`, :meth:`Reconstruction.save`
    The options, validated once; the whole job in four stages (prepare the problem,
    choose weights, solve the patches, assemble); the outputs written to a folder.
:func:`spectral_errors`, :func:`colour_errors`, :func:`registration_scale`, :func:`patch_weights`
    Evaluation metrics (§4.4.1–4.4.2): MRAE, RMSE, GOF, SSIM; per-band registration.
:func:`residual_aberration`, :func:`patch_regions`, :func:`ideal_image`
    Residual chromatic aberration in strips inside ColorChecker patch edges (§4.4.3).
:data:`BASELINES`, :func:`baseline`
    Comparison methods (§4.6): bilinear, Malvar, Menon demosaicing, then optional warping.
:func:`baseline_images`, :func:`evaluate`, :class:`Evaluation`
    Every baseline of one raw image, and a scoreboard of named estimates (residual
    aberration, colour and spectral errors against a truth) (``labkit evaluate``).
"""

from reconstruction.baselines import BASELINES, baseline
from reconstruction.evaluate.evaluation import Evaluation, Score, baseline_images, evaluate
from reconstruction.evaluate.metrics import (
    ColourErrors,
    SpectralErrors,
    colour_errors,
    patch_weights,
    registration_scale,
    spectral_errors,
)
from reconstruction.evaluate.residual_aberration import (
    PatchRegions,
    ResidualAberration,
    SpectralStripErrors,
    ideal_image,
    patch_regions,
    residual_aberration,
    spectral_strip_errors,
)
from reconstruction.model.image_formation import ImageFormation, LatentSpace, build_formation
from reconstruction.model.prior_terms import PRIORS, PriorTerm, prior_terms
from reconstruction.model.problem import Problem
from reconstruction.options import OptionError, ReconstructOptions
from reconstruction.reconstruct import Reconstruction, reconstruct
from reconstruction.solve.patches import PatchOptions, SolverOptions, reconstruct_patches
from reconstruction.solve.weights import CRITERIA, WeightSelection, select_weights

__all__ = [
    "BASELINES",
    "CRITERIA",
    "PRIORS",
    "ColourErrors",
    "Evaluation",
    "ImageFormation",
    "LatentSpace",
    "OptionError",
    "PatchOptions",
    "PatchRegions",
    "PriorTerm",
    "Problem",
    "ReconstructOptions",
    "Reconstruction",
    "ResidualAberration",
    "Score",
    "SolverOptions",
    "SpectralErrors",
    "SpectralStripErrors",
    "WeightSelection",
    "baseline",
    "baseline_images",
    "build_formation",
    "colour_errors",
    "evaluate",
    "ideal_image",
    "patch_regions",
    "patch_weights",
    "prior_terms",
    "reconstruct",
    "reconstruct_patches",
    "registration_scale",
    "residual_aberration",
    "select_weights",
    "spectral_errors",
    "spectral_strip_errors",
]
