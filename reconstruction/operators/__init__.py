"""Linear operators of problem (3.1): M, Ω, Φ, B and the priors' differences (thesis §3.2–3.5)."""

from reconstruction.operators._base import Adjoint, Composition, DotTest, LinearOperator, dot_test

__all__ = ["Adjoint", "Composition", "DotTest", "LinearOperator", "dot_test"]
