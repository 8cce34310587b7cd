"""Scoring reconstructions and the methods they are compared with (thesis ch. 4).

Contents
--------
:mod:`~reconstruction.evaluate.metrics`
    Spectral and colour error metrics (MRAE, RMSE, GOF, SSIM) and per-band registration.
:mod:`~reconstruction.evaluate.residual_aberration`
    Residual chromatic aberration in strips inside the chart patches' edges.
:mod:`~reconstruction.evaluate.evaluation`
    A scoreboard of named estimates against a truth, every baseline included.
:mod:`~reconstruction.evaluate.chart_scores`
    A reconstruction of a labelled chart scored against its spectra and edges.
"""
