"""Learning-curve plots from SB3's ``EvalCallback`` output (``evaluations.npz``) or a DAgger run's summary
(``summary.json``, committed beside each model as ``training_summary.json``), one run or several.

Command line (e.g. the seeds of a baseline side by side)::

    python -m suture_gym.baselines.plotting runs/ppo_NeedleInsert_s*/eval/evaluations.npz --out curve.png --title "PPO"
    python -m suture_gym.baselines.plotting models/WoundClosure/seed*/training_summary.json --out curve.png
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np


def load_curve(path: str | Path) -> dict[str, np.ndarray]:
    """One run's learning curve as ``{"timesteps": (E,), "results": (E, n), "successes": (E, n)}``.

    ``path`` is an ``evaluations.npz`` of ``EvalCallback`` (one column per evaluation episode), or a DAgger run's
    ``summary.json``/``training_summary.json`` (:func:`suture_gym.baselines.dagger.train_dagger`), whose learner-alone
    iterations (``beta`` 0) are the points: at the env steps gathered before the rollout, the iteration's mean
    return and success rate (one column: the summary keeps no per-episode figures).
    """
    path = Path(path)
    if path.suffix != ".json":
        with np.load(path) as data:
            return {key: data[key] for key in data.files}
    summary = json.loads(path.read_text())
    if not isinstance(summary, dict) or not isinstance(summary.get("iterations"), list):
        raise ValueError(f"{path} is not a DAgger summary: it has no 'iterations' list")
    alone = [it for it in summary["iterations"] if it.get("beta") == 0.0]
    if not alone:
        raise ValueError(f"{path} has no learner-alone iteration (beta 0) to plot")
    return {"timesteps": np.array([it["checkpoint_steps"] - it["steps"] for it in alone]),
            "results": np.array([[it["mean_return"]] for it in alone]),
            "successes": np.array([[it["success_rate"]] for it in alone])}


def _run_name(path: Path) -> str:
    """A curve file's default legend label: its run directory (``<run>/eval/evaluations.npz``), the folder of a
    summary (``models/<Task>/seed<k>/training_summary.json``), else the file's stem."""
    if path.parent.name == "eval":
        return path.parent.parent.name
    return path.parent.name if path.suffix == ".json" else path.stem


def plot_learning_curve(evaluations: str | Path | Sequence[str | Path], out_png: str | Path, title: str = "",
                        labels: Sequence[str] | None = None) -> Path:
    """Plot the evaluation return and, when recorded, the success rate against env steps.

    One run is drawn as its mean with a ± std band over the evaluation episodes (where it has several); several
    runs (seeds, or variants) as one labelled line each.

    Args:
        evaluations: one ``evaluations.npz`` written by ``EvalCallback`` (keys ``timesteps (E,)``,
            ``results (E, episodes)``, optionally ``successes (E, episodes)``) or DAgger summary (see
            :func:`load_curve`), or a sequence of them.
        out_png: where to write the figure (a small PNG, ~100 dpi).
        title: figure title.
        labels: one legend label per file (default: the run directory's name, or the folder of a summary).

    Returns:
        ``out_png`` as a Path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = [Path(evaluations)] if isinstance(evaluations, (str, Path)) else [Path(p) for p in evaluations]
    if not paths:
        raise ValueError("evaluations must name at least one evaluations.npz or DAgger summary")
    if labels is None:
        labels = [_run_name(p) for p in paths]
    if len(labels) != len(paths):
        raise ValueError(f"got {len(labels)} labels for {len(paths)} evaluation files")
    runs = [load_curve(path) for path in paths]
    has_success = any("successes" in r and r["successes"].size and len(r["successes"]) == len(r["timesteps"])
                      for r in runs)
    fig, axes = plt.subplots(1, 2 if has_success else 1, figsize=(9 if has_success else 5, 3.2), dpi=100)
    axes = np.atleast_1d(axes)
    single = len(runs) == 1
    for k, (run, label) in enumerate(zip(runs, labels, strict=True)):
        color = "tab:blue" if single else f"C{k}"
        steps = run["timesteps"]
        mean, std = run["results"].mean(axis=1), run["results"].std(axis=1)
        axes[0].plot(steps, mean, color=color, label=None if single else label)
        if single and run["results"].shape[1] > 1:
            axes[0].fill_between(steps, mean - std, mean + std, color=color, alpha=0.2)
        successes = run.get("successes")
        if has_success and successes is not None and successes.size and len(successes) == len(steps):
            axes[1].plot(steps, successes.mean(axis=1) * 100.0, color="tab:green" if single else color)
    axes[0].set_xlabel("env steps")
    axes[0].set_ylabel("evaluation return")
    axes[0].grid(alpha=0.3)
    if not single:
        axes[0].legend(fontsize=8)
    if has_success:
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Plot learning curves from EvalCallback evaluations.npz files or DAgger summaries.")
    parser.add_argument("evaluations", nargs="+", help="evaluations.npz or DAgger summary.json files, one per run")
    parser.add_argument("--out", required=True, help="output PNG")
    parser.add_argument("--title", default="")
    parser.add_argument("--labels", nargs="+", default=None, help="one legend label per file")
    args = parser.parse_args(argv)
    print(plot_learning_curve(args.evaluations, args.out, title=args.title, labels=args.labels))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
