"""One error hierarchy for the whole ``core`` library.

Every public function in ``core`` raises a subclass of :class:`CoreError` for bad input, naming
the argument (or file and field) that is wrong. ``assert`` is used only for internal invariants.
"""

from __future__ import annotations


class CoreError(Exception):
    """Base class of every error raised on purpose by ``core``."""


class ShapeError(CoreError, ValueError):
    """A tensor or array argument has the wrong shape, dtype or device."""


class ConfigError(CoreError, ValueError):
    """A setting or argument value is out of range or inconsistent with another."""


class NumericalError(CoreError, ArithmeticError):
    """A value is NaN or Inf, or a computation left its numerically valid range."""


class ModelLoadError(CoreError, RuntimeError):
    """A learned model file is missing, corrupt, or does not match the expected contract."""


class FormatError(CoreError, ValueError):
    """A file on disk (EXR, HDR, PNG, JSON, bundle member) is malformed or unsupported."""


class BundleError(FormatError):
    """A scene bundle is malformed. ``path`` names the file and ``field`` the offending field."""

    def __init__(self, message: str, path: str | None = None, field: str | None = None):
        self.path = path
        self.field = field
        where = ""
        if path:
            where = f"{path}"
            if field:
                where += f" [{field}]"
            where += ": "
        elif field:
            where = f"[{field}]: "
        super().__init__(where + message)


class DependencyError(CoreError, ImportError):
    """An optional dependency needed for this call (e.g. Mitsuba) is not installed."""
