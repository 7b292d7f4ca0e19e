"""Unit constants, one per fact. Code and files are SI (Tesla, metres, seconds); papers quote nT."""

NT: float = 1e-9
"""One nanotesla in Tesla."""

MU0_OVER_4PI: float = 1e-7
"""mu_0 / (4 pi) in T m / A."""

NS_PER_S: int = 1_000_000_000
"""Nanoseconds per second: stamps are integer nanoseconds (ROS ``sec`` and ``nanosec``)."""
