"""The operator's web console (``daror console --web``): the facade's requests, status and live data in a browser.

Needs the ``web`` extra (FastAPI, uvicorn, websockets); :func:`require_web_extra` says how to get it.
Like the text console it imports only the facade and the console's own modules
(``tests/test_boundaries.py``); every button posts a console line, checked and answered as typed.
"""

from __future__ import annotations

from daror_runtime.errors import InputError

WEB_EXTRA_HINT = "the web console needs the web extra: pip install 'daror-runtime[web]'"


class WebExtraMissingError(InputError):
    """``daror console --web`` without FastAPI, uvicorn or websockets installed (exit 2, one line)."""


def require_web_extra() -> None:
    """Raises :class:`WebExtraMissingError` (one line: how to install) unless the web extra is installed."""
    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
        import websockets  # noqa: F401
    except ImportError as exc:
        raise WebExtraMissingError(f"{WEB_EXTRA_HINT} ({exc.name} is missing)") from None
