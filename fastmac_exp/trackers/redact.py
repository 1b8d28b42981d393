"""Credentials in URIs (`https://user:password@host`) never reach a file or the console.

A tracking server's URI may carry a user and password (tracker.mlflow.uri); the run directory's configs,
Hydra's copies of them, the logs and the trackers' params get the URI with them replaced by `***`.
"""

from __future__ import annotations

import logging
import re
from typing import Any
from urllib.parse import unquote, urlsplit, urlunsplit

MASK = "***"
# scheme://userinfo@ : the userinfo (user, or user:password) is what goes; Hydra writes overrides with
# their colons escaped (http\://user\:pw@host)
_USERINFO = re.compile(r"(?P<scheme>\b[A-Za-z][A-Za-z0-9+.-]*\\?://)(?P<userinfo>[^/@\s'\"]+)@")


def split_credentials(uri: str) -> tuple[str, str | None, str | None]:
    """(the URI without user:password, the user, the password), user and password percent-decoded."""
    parts = urlsplit(uri)
    if not parts.netloc or "@" not in parts.netloc:
        return uri, None, None
    userinfo, host = parts.netloc.rsplit("@", 1)
    user, _, password = userinfo.partition(":")
    clean = urlunsplit((parts.scheme, host, parts.path, parts.query, parts.fragment))
    return clean, unquote(user) or None, unquote(password) if password else None


def redact_text(text: str) -> str:
    """`text` with the userinfo of every URI in it masked."""
    return _USERINFO.sub(lambda m: f"{m['scheme']}{MASK}@", text) if "@" in text else text


def redact(obj: Any) -> Any:
    """A copy of a plain container (dicts, lists, strings) with every URI's userinfo masked."""
    if isinstance(obj, str):
        return redact_text(obj)
    if isinstance(obj, dict):
        return {k: redact(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(redact(v) for v in obj)
    return obj


_installed = False


def redact_logs() -> None:
    """Mask URI credentials in every log record from now on (Hydra's launchers log a sweep's overrides,
    the console and run.log would show a tracker URI's password). Idempotent."""
    global _installed
    if _installed:
        return
    make = logging.getLogRecordFactory()

    def factory(*args: Any, **kwargs: Any) -> logging.LogRecord:
        record = make(*args, **kwargs)
        if "@" in str(record.msg) or any("@" in str(a) for a in (record.args or ())):
            record.msg = redact_text(record.getMessage())
            record.args = None
        return record

    logging.setLogRecordFactory(factory)
    _installed = True
