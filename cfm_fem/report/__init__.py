"""Reports a person would rather look at: PNG figures (matplotlib, Agg) and self-contained HTML.

Nothing here opens files: figures come back as PNG bytes and reports as HTML text; the writers
(:mod:`cfm_fem.io.run_files`) put them on disk atomically.
"""

from .html import HtmlReport
from .plots import (
    fig4_curve,
    fig4_plane,
    fig10_systematic,
    hist_figure,
    interval_figure,
    png_bytes,
    residual_figure,
)

__all__ = [
    "HtmlReport",
    "fig4_curve",
    "fig4_plane",
    "fig10_systematic",
    "hist_figure",
    "interval_figure",
    "png_bytes",
    "residual_figure",
]
