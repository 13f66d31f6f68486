"""Learning-curve plot from SB3's ``EvalCallback`` output (``evaluations.npz``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_learning_curve(evaluations: str | Path, out_png: str | Path, title: str = "") -> Path:
    """Plot mean ± std evaluation return and, when recorded, the success rate against env steps.

    Args:
        evaluations: ``evaluations.npz`` written by ``EvalCallback`` (keys ``timesteps (E,)``,
            ``results (E, episodes)``, optionally ``successes (E, episodes)``).
        out_png: where to write the figure (a small PNG, ~100 dpi).

    Returns:
        ``out_png`` as a Path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = np.load(evaluations)
    steps = data["timesteps"]
    results = data["results"]
    has_success = "successes" in data and len(data["successes"]) == len(steps) and data["successes"].size
    fig, axes = plt.subplots(1, 2 if has_success else 1, figsize=(9 if has_success else 5, 3.2), dpi=100)
    axes = np.atleast_1d(axes)
    mean, std = results.mean(axis=1), results.std(axis=1)
    axes[0].plot(steps, mean, color="tab:blue")
    axes[0].fill_between(steps, mean - std, mean + std, color="tab:blue", alpha=0.2)
    axes[0].set_xlabel("env steps")
    axes[0].set_ylabel("evaluation return")
    axes[0].grid(alpha=0.3)
    if has_success:
        axes[1].plot(steps, data["successes"].mean(axis=1) * 100.0, color="tab:green")
        axes[1].set_xlabel("env steps")
        axes[1].set_ylabel("success rate (%)")
        axes[1].set_ylim(-2, 102)
        axes[1].grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png)
    plt.close(fig)
    return out_png
