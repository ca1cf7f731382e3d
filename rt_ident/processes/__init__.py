"""The helper processes a run starts beside the loop, and how the loop hands them work without
blocking: the shared-memory rings, the telemetry process (rerun), the recorder process (Parquet), the
job processes (the fit and the controller redesign), the emulated devices, and the guard that starts,
watches and ends them.

May import :mod:`rt_ident.outputs`, :mod:`rt_ident.control`, :mod:`rt_ident.estimators`,
:mod:`drivers` and :mod:`rt_ident.axis`.
"""
