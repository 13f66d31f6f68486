"""Plot the force of one needle insertion through the silicone pad (the ``insertion_force_profile`` run).

Usage::

    python scripts/plot_insertion_force.py                    # writes docs/media/insertion_force.png
    python scripts/plot_insertion_force.py --out other.png

Runs :func:`suture_gym.measure.insertion.drive_insertion` on :func:`suture_gym.measure.insertion.insertion_pad`
and plots, against time, the tissue's reaction along the needle's arc (what the holder feels) and, for
comparison, the sum of the force model's own terms (the tip's contact force, the cutting force and the axial
friction), with the entry and exit peaks marked (the exit peak only if the tip left the pad).
"""

from __future__ import annotations

import argparse
import math

from _common import ROOT, configure

configure(threads=1)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from suture_gym.measure.insertion import (  # noqa: E402
    COUPLING,
    INSERTION_DURATION,
    drive_insertion,
    insertion_pad,
    insertion_profile,
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "docs" / "media" / "insertion_force.png"), help="PNG path")
    args = parser.parse_args(argv)
    scene, circle = insertion_pad()
    run = drive_insertion(scene, circle, INSERTION_DURATION)
    profile = insertion_profile(run, COUPLING.puncture_force)
    t = run["time"]
    model_force = run["tip_force"] + run["cut_force"] + run["friction_force"]
    fig, ax = plt.subplots(figsize=(6.4, 3.4), dpi=110)
    ax.plot(t, run["force"], lw=0.8, color="C0", label="reaction along the arc (holder)")
    ax.plot(t, model_force, lw=0.8, color="C1", label="tip + cutting + friction terms")
    ax.axhline(COUPLING.puncture_force, color="0.6", lw=0.6, ls="--", label="entry / exit thresholds")
    ax.axhline(COUPLING.exit_puncture_force, color="0.6", lw=0.6, ls="--")
    for name, time_key, peak_key, colour in (("entry", "puncture_time_s", "entry_peak_n", "C3"),
                                             ("exit", "exit_time_s", "exit_peak_n", "C2")):  # fmt: skip
        if math.isfinite(profile[peak_key]):
            ax.plot([profile[time_key]], [profile[peak_key]], "v", color=colour, ms=7,
                    label=f"{name} peak {profile[peak_key]:.2f} N")  # fmt: skip
    if not math.isfinite(profile["exit_peak_n"]):
        ax.text(0.98, 0.05, "no exit peak: the tip did not leave the pad", transform=ax.transAxes, ha="right",
                fontsize=8, color="C2")  # fmt: skip
    ax.set_xlabel("time (s)")
    ax.set_ylabel("force along the needle's path (N)")
    ax.set_title("Semicircle needle through a 150 kPa silicone pad at 1 rad/s", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out)
    print(f"wrote {args.out}: entry peak {profile['entry_peak_n']:.3f} N, exit peak {profile['exit_peak_n']:.3f} N")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
