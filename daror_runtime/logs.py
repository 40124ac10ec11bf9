"""Structured logging, configured once per process.

People read one line per event on stderr; machines read JSON lines (one object per event) from
an optional file. The two sinks have their own levels: the JSON audit file keeps everything from
``info`` up while the console stays quiet by default. Library code only ever calls
``structlog.get_logger(__name__)`` and logs events with key-value context.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any, TextIO

import structlog

_configured = False
_json_handle: TextIO | None = None


def _level(name: str) -> int:
    return logging.getLevelNamesMapping()[name.upper()]


def configure_logging(
    console_level: str = "warning",
    json_path: Path | str | None = None,
    json_level: str = "info",
    stream: TextIO | None = None,
) -> None:
    """Readable lines at ``console_level`` and up to ``stream`` (stderr); JSON lines to ``json_path``.

    Calling it again replaces the previous configuration (tests and the CLI rely on this).
    """
    global _configured, _json_handle
    if _json_handle is not None:
        _json_handle.close()
        _json_handle = None
    console_threshold = _level(console_level)
    json_threshold = _level(json_level)
    if json_path is not None:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        _json_handle = open(json_path, "a", encoding="utf-8")  # noqa: SIM115 - lives as long as the config
    json_handle = _json_handle
    console = structlog.dev.ConsoleRenderer(colors=False)
    json_renderer = structlog.processors.JSONRenderer()

    def route(logger: Any, method: str, event_dict: dict[str, Any]) -> str:
        level = _level(event_dict.get("level", method))
        if json_handle is not None and level >= json_threshold:
            json_handle.write(json_renderer(logger, method, dict(event_dict)) + "\n")
            json_handle.flush()
        if level < console_threshold:
            raise structlog.DropEvent
        return console(logger, method, event_dict)

    floor = min(console_threshold, json_threshold) if json_handle is not None else console_threshold
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            route,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(floor),
        logger_factory=structlog.PrintLoggerFactory(file=stream if stream is not None else sys.stderr),
        cache_logger_on_first_use=False,
    )
    _configured = True


def ensure_logging() -> None:
    """Configure the defaults unless something already configured logging."""
    if not _configured:
        configure_logging()
