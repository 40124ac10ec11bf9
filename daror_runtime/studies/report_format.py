"""What the studies' reports share: a figure as PNG bytes, a number as a table cell, the files written."""

from __future__ import annotations

import io
from pathlib import Path

from matplotlib.figure import Figure

from daror_runtime.util.atomic import atomic_path, write_text_atomic


def png_bytes(figure: Figure, dpi: int) -> bytes:
    """``figure`` rendered as PNG at ``dpi`` dots per inch (an Agg canvas must be attached)."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


def cell(value: float | None, digits: int = 4) -> str:
    """``value`` to ``digits`` significant digits; ``-`` for None (nothing was fitted)."""
    return "-" if value is None else f"{value:.{digits}g}"


def write_study_files(
    folder: Path, paths: tuple[Path, Path, Path], document: str, png: bytes, markdown: str
) -> tuple[Path, Path, Path]:
    """Write a study's (JSON, PNG, Markdown) ``paths`` in ``folder`` (created if missing), each atomically.

    Everything is rendered before this is called, so a rendering error leaves no partial set; the
    JSON is written last: its presence marks a complete set for scripts that poll the folder.
    """
    json_path, png_path, md_path = paths
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(png_path) as tmp:
        tmp.write_bytes(png)
    write_text_atomic(md_path, markdown)
    write_text_atomic(json_path, document)
    return paths
