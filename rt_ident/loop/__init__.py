"""The real-time loop: read -> estimate -> control -> write on absolute deadlines, each axis's tick in one
compiled call (``tick_kernel``, ``tick_core``), its telemetry windows, the ticker, the host-side safety
checks, loop stalls and the host under the loop (real-time setup, the idle poller).

May import :mod:`rt_ident.processes`, :mod:`rt_ident.outputs`, :mod:`rt_ident.control`,
:mod:`rt_ident.estimators`, :mod:`drivers` and :mod:`rt_ident.axis`.
"""
