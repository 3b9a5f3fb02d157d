"""Figures of a `reproduce` run: Fig. 5's two panels from its results (matplotlib, Agg)."""

from __future__ import annotations

import io
import os

import numpy as np

from gpguided_jax import checkpoints
from gpguided_jax import stats as stats_lib


def plot_fig5(results: dict[str, np.ndarray], out_dir: str) -> list[str]:
    """Fig. 5: (a) mean reward per step vs updates, (b) exploration std; mean and 95% band over
    seeds (a band of zero width for one seed). Writes fig5_reward.png and fig5_exploration.png to
    `out_dir` (atomically) and returns their paths.

    Args:
      results: methods (M,) and records mean_reward, exploration_std of shape (M, seeds, updates),
        as in results.npz.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for field, ylabel, name in [
        ("mean_reward", "average reward per step of an episode", "fig5_reward.png"),
        ("exploration_std", "exploration std (mean over visited states) [N m]", "fig5_exploration.png"),
    ]:
        fig, ax = plt.subplots(figsize=(7, 4.2))
        data = results[field]
        for m, curves in zip(results["methods"], data):
            mean, half = stats_lib.t_interval(curves)
            if curves.shape[0] < 2:
                half = np.zeros_like(mean)
            x = np.arange(1, curves.shape[1] + 1)
            ax.plot(x, mean, label=str(m))
            ax.fill_between(x, mean - half, mean + half, alpha=0.25)
        ax.set_xlabel("gradient updates performed")
        ax.set_ylabel(ylabel)
        ax.legend()
        ax.grid(alpha=0.3)
        panel = "(a)" if field == "mean_reward" else "(b)"
        ax.set_title(f"{panel} mean and 95% CI over {data.shape[1]} seeds")
        fig.tight_layout()
        path = os.path.join(out_dir, name)
        buf = io.BytesIO()
        fig.savefig(buf, dpi=120, format="png")
        plt.close(fig)
        checkpoints.atomic_write_bytes(path, buf.getvalue())
        paths.append(path)
    return paths
