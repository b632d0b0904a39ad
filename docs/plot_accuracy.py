#!/usr/bin/env python3
"""Plots error against time from `radiosity bench-accuracy` output.

    ./target/release/radiosity bench-accuracy > docs/accuracy.json
    ./target/release/radiosity bench-accuracy --budgets 3000000,10000000 --reference-factor 4 \
        > docs/accuracy-final.json
    pip install matplotlib
    python3 docs/plot_accuracy.py docs/accuracy.png docs/accuracy.json docs/accuracy-final.json

Plotted: the area-weighted RMS of the per-patch relative error over lit, non-emitting patches
(`lit_error`). The furnace is left out: everything in it emits (it has no such patches), and it is
exact (to rounding) at every budget.
"""
import json
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main(target, sources):
    scenes = {}
    for source in sources:
        with open(source) as f:
            report = json.load(f)
        for p in report["points"]:
            if p["lit_error"] is not None:
                scenes.setdefault(p["scene"], []).append(p)
    for points in scenes.values():
        points.sort(key=lambda p: p["lines"])
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for scene, points in scenes.items():
        xs = [p["seconds"] for p in points]
        ys = [p["lit_error"] for p in points]
        ax.loglog(xs, ys, "o-", label=f"{scene} ({points[0]['frames']} frames)")
        for p in points:
            ax.annotate(f"{p['lines'] / 1e6:.2g}M", (p["seconds"], p["lit_error"]),
                        textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xlabel("wall time: trace + tally + solve every frame (s, 2 cores)")
    ax.set_ylabel("per-patch relative error, RMS over lit non-emitting patches")
    ax.set_title("Speed against accuracy (labels: lines)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(target)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
