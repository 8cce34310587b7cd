"""The model of problem (3.1): what is solved, not how (thesis §3.2–3.5).

Contents
--------
:mod:`~reconstruction.model.operators`
    M, Ω, Φ, B and the priors' difference operators, each with adjoint and dot test.
:mod:`~reconstruction.model.image_formation`
    The latent space and A = M·Ω·Φ·B (3.1), or its direct-colour form (3.27), per patch.
:mod:`~reconstruction.model.prior_terms`
    The regularisation terms and the prior combinations of Table 3.1.
:mod:`~reconstruction.model.band_balance`
    Each band's spatial smoothing scaled to how well the data determine it.
:mod:`~reconstruction.model.edge_weights`
    Edge weights of the edge-guided L2 prior, from a demosaiced guide image.
:mod:`~reconstruction.model.problem`
    One patch's problem: data, A, priors, weights, non-negativity.
"""
