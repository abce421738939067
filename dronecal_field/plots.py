"""Plots of the engine's results (matplotlib, Agg backend, files only)."""

from __future__ import annotations

import os

import numpy as np


def plot_convergence(running_mean: np.ndarray, path: str | os.PathLike, title: str = "Convergence of the RMS estimate") -> None:
    """The paper's Figure 1: running mean of the RMS reprojection error against the number of trials."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = np.arange(1, running_mean.size + 1)
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    ax.plot(k, running_mean, lw=1.2)
    ax.axhline(running_mean[-1], color="grey", lw=0.8, ls="--")
    ax.set_xlabel("Monte-Carlo iterations k")
    ax.set_ylabel("mean RMS reprojection error (px)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
