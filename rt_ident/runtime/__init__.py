"""The real-time run: the loop and its scheduler, the shared-memory rings, the fit worker,
telemetry and the dashboard, the recorder and its reader, safety, the emulator processes,
and :mod:`rt_ident.runtime.run`, the composition root that joins config, backend,
estimators, loop, telemetry and recording.

May import :mod:`rt_ident.axis`, :mod:`rt_ident.estimators` and :mod:`drivers`.
"""
