#!/usr/bin/env python3
"""Plots error against time from `radiosity bench-accuracy` output.

    ./target/release/radiosity bench-accuracy > docs/accuracy.json
    ./target/release/radiosity bench-accuracy --budgets 3000000,10000000 --gain-lines 0 \
        > docs/accuracy-final.json
    pip install matplotlib
    python3 docs/plot_accuracy.py docs/accuracy.png docs/accuracy.json docs/accuracy-final.json

Plotted against the wall time of the whole bake (trace, patches, pieces, every frame): the
area-weighted RMS of the per-patch relative error over lit, non-emitting patches (`lit_error`)
and, where the reference is the path tracer, the error at points (`point_error`, what a
lightmap shows; hollow downward triangles where it is below what the reference resolves,
drawn at that resolution). The furnace is left out: everything in it emits (it has no such patches), and
it is exact (to rounding) at every budget.
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
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), dpi=120)
    for ax, key, label in [
        (axes[0], "lit_error", "per-patch relative error (RMS, lit non-emitting)"),
        (axes[1], "point_error", "relative L2 error at points (what a lightmap shows)"),
    ]:
        for scene, points in scenes.items():
            points = [p for p in points if p.get(key) is not None]
            if not points:
                continue
            # An error at points below what the reference resolves is drawn hollow at that
            # resolution: an upper bound, not a value.
            floor = "point_resolution" if key == "point_error" else None
            ys = [max(p[key], p[floor]) if floor else p[key] for p in points]
            xs = [p["seconds"] for p in points]
            line, = ax.loglog(xs, ys, "-", label=f"{scene} ({points[0]['frames']} frames)")
            for p, x, y in zip(points, xs, ys):
                bound = floor is not None and p[key] < p[floor]
                ax.plot([x], [y], "v" if bound else "o", color=line.get_color(),
                         markerfacecolor="none" if bound else line.get_color())
                ax.annotate(f"{p['lines'] / 1e6:.2g}M, {p['patches']}", (x, y),
                            textcoords="offset points", xytext=(4, 4), fontsize=7)
        ax.set_xlabel("wall time of the bake: trace, patches, pieces, every frame (s, 2 cores)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Speed against accuracy, against physics (labels: lines, patches)")
    fig.tight_layout()
    fig.savefig(target)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
