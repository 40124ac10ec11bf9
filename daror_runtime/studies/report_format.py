"""What the studies' reports share: a figure as PNG bytes, a number as a table cell."""

from __future__ import annotations

import io

from matplotlib.figure import Figure


def png_bytes(figure: Figure, dpi: int) -> bytes:
    """``figure`` rendered as PNG at ``dpi`` dots per inch (an Agg canvas must be attached)."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


def cell(value: float | None, digits: int = 4) -> str:
    """``value`` to ``digits`` significant digits; ``-`` for None (nothing was fitted)."""
    return "-" if value is None else f"{value:.{digits}g}"
