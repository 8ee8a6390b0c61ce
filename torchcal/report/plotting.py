"""Matplotlib for report figures, drawn without a display.

matplotlib stays off torchcal's import path (it costs about half a second and only figures need
it): :func:`pyplot` imports it on the first figure, with the non-interactive Agg backend."""
from __future__ import annotations

__all__ = ["pyplot"]


def pyplot():
    """The ``matplotlib.pyplot`` module, set to the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
