"""The axis's physics: the two-inertia model (Eqs. 1-3, 8), its parameters and modal values,
the integrators (Newmark-beta, Eqs. 4-6) and compiled simulation kernels, the simulated plant
with its sensors, the Schroeder excitation and the time-step criterion (Table 2).

Imports numpy, scipy and numba, and of this project only :mod:`rt_ident.errors`.
"""
