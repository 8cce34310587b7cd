"""Solving problem (3.1) on an image: the solvers, the weights, the patches (thesis §3.6–3.8).

Contents
--------
:mod:`~reconstruction.solve.solvers`
    ADMM, the exact non-negative optimum and the direct solve, chosen by name.
:mod:`~reconstruction.solve.weights`
    The regularisation weights' search (Algorithm 3) and its criteria.
:mod:`~reconstruction.solve.patches`
    The patch-wise driver: which patches need Φ, which are flat, one task per patch.
:mod:`~reconstruction.solve.worker_pool`
    The opt-in pool of worker processes the patches' tasks can run on.
"""
