"""rt_ident: identification of a machine-tool axis modelled as a two-inertia spring-damper."""

from rt_ident.axis.params import AxisParams, thomson_x

__version__ = "0.1.0"
__all__ = ["AxisParams", "thomson_x", "__version__"]
