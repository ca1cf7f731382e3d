"""rt_ident: identification of a machine-tool axis modelled as a two-inertia spring-damper."""

from rt_ident import kernel_cache

kernel_cache.sync()          # before any compiled kernel is loaded from numba's cache

from rt_ident.axis.params import AxisParams, thomson_x  # noqa: E402

__version__ = "0.1.0"
__all__ = ["AxisParams", "thomson_x", "__version__"]
