"""Unit constants. Code and files are SI (Tesla, metres); papers quote nT."""

NT: float = 1e-9
"""One nanotesla in Tesla."""

MU0_OVER_4PI: float = 1e-7
"""mu_0 / (4 pi) in T m / A."""
