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

    With `env_steps` in `results`, the environment steps spent are on the x-axis too: on a
    second axis above the updates when every method spends them alike, else as the x-axis itself
    (methods that differ in steps per update are compared at equal experience).

    Args:
      results: methods (M,) and records mean_reward, exploration_std of shape (M, seeds, updates),
        as in results.npz (NaN past a method's last update); optionally env_steps (M, updates).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = results.get("env_steps")
    if steps is not None:
        steps = np.asarray(steps, float)
    alike = steps is None or bool(np.all((steps == steps[:1]) | np.isnan(steps)))
    paths = []
    for field, ylabel, name in [
        ("mean_reward", "average reward per step of an episode", "fig5_reward.png"),
        ("exploration_std", "exploration std (mean over visited states) [N m]", "fig5_exploration.png"),
    ]:
        fig, ax = plt.subplots(figsize=(7, 4.2))
        data = results[field]
        for i, (m, curves) in enumerate(zip(results["methods"], data)):
            n = int(np.sum(~np.all(np.isnan(np.asarray(curves, float)), axis=0)))
            curves = np.asarray(curves, float)[:, :n]
            mean, half = stats_lib.t_interval(curves)
            if curves.shape[0] < 2:
                half = np.zeros_like(mean)
            x = np.arange(1, n + 1) if alike else steps[i, :n]
            ax.plot(x, mean, label=str(m))
            ax.fill_between(x, mean - half, mean + half, alpha=0.25)
        ax.set_xlabel("updates performed" if alike else "environment steps")
        if alike and steps is not None and steps.shape[1] > 1:
            first, per = steps[0, 0], max(steps[0, 1] - steps[0, 0], 1.0)
            top = ax.secondary_xaxis("top", functions=(
                lambda u, a=first, b=per: a + b * (u - 1), lambda e, a=first, b=per: 1 + (e - a) / b))
            top.set_xlabel("environment steps")
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
