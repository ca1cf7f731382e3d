"""The benchmarks behind ``rt-ident bench``: the compiled kernels against their peers, the loop's
capacity and soak, the XY tick budget, fixed against adaptive control, and the per-sample estimator.

May import everything below :mod:`rt_ident.cli` but :mod:`rt_ident.fleet`.
"""
