"""rt_ident: identification of a machine-tool axis modelled as a two-inertia spring-damper."""

import os

# A real-time run locks every page its process maps (mlockall): Arrow's default mimalloc pool reserves a
# 1 GiB arena at its first allocation (a recording read or written in-process), which the lock would fault
# in and pin, seconds before the loop starts. The system allocator maps only what it uses. Read at
# pyarrow's import, so it holds where rt_ident is imported first; a user's own setting is kept.
os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")

from rt_ident import kernel_cache  # noqa: E402

kernel_cache.sync()          # before any compiled kernel is loaded from numba's cache

from rt_ident.axis.params import AxisParams, thomson_x  # noqa: E402

__version__ = "0.1.0"
__all__ = ["AxisParams", "thomson_x", "__version__"]
