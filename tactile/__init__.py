"""Tactile physics of the two-layer nonlinear element (paper §II.B, §III): pure numpy."""
