"""One exception hierarchy for the whole product.

Every error raised on purpose by :mod:`rt_ident` or :mod:`drivers` derives from
:class:`RtIdentError`, so a caller (the CLI, the loop) can handle "our" errors in
one place and let genuine bugs propagate.
"""

from __future__ import annotations


class RtIdentError(Exception):
    """Root of every error this package raises on purpose."""


class ConfigError(RtIdentError, ValueError):
    """Invalid configuration or parameter value. The message names the field."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


class EstimationError(RtIdentError):
    """An estimator cannot produce an answer from the data it was given."""


class DataError(RtIdentError, ValueError):
    """Input data (a recording, a CSV, arrays) is malformed."""


class MissingExtra(RtIdentError):
    """A feature needs a package the core install leaves out (an optional extra of the project)."""


def require(module: str, extra: str, what: str) -> None:
    """Raise :class:`MissingExtra` in one line when ``module`` cannot be imported: ``what`` needs the
    ``extra`` of ``pip install 'rt-ident[extra]'``."""
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise MissingExtra(f"{what} needs {module}: pip install 'rt-ident[{extra}]' (or -e '.[{extra}]' in a checkout)")
