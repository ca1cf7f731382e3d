"""The composition roots: a run built from its config - the per-axis parts (``build``), the checks
before anything starts (``preflight``), the run itself on one or more axes (``run``, ``axes``) and the
same loop faster than real time (``offline``).

May import everything below :mod:`rt_ident.bench` and :mod:`rt_ident.reports`.
"""
