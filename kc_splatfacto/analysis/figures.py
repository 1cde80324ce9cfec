"""Figures for reports and diagnostics: matplotlib on its file-only backend, PNGs written atomically."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from kc_splatfacto.atomic import atomic_write


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (no display needed); imported on first use, not at package import."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, dpi: int) -> Path:
    """Lay ``fig`` out tightly, write it to ``path`` as PNG (folder created, atomically) and close it."""
    plt = pyplot()
    try:
        fig.tight_layout()
        return atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"))
    finally:
        plt.close(fig)
