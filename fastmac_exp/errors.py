"""Exceptions that carry a message meant for the user (what is wrong and where)."""


class FastMacError(Exception):
    """Base class of the errors this package raises on purpose."""


class InputError(FastMacError, ValueError):
    """Bad user input: a missing or malformed file, a bad config value, degenerate data."""


class RegistrationFailed(FastMacError, RuntimeError):
    """MAC could not produce a pose for this pair (no edges, no cliques, too few correspondences)."""


class BackendUnavailable(FastMacError, RuntimeError):
    """The requested backend is not built or not installed."""


def own_error(exc: BaseException | None) -> FastMacError | None:
    """The project's error behind `exc` (Hydra wraps constructor errors in InstantiationException)."""
    seen = 0
    while exc is not None and seen < 10:
        if isinstance(exc, FastMacError):
            return exc
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None
