#!/usr/bin/env python3
"""Plots per-patch error against patches from `radiosity bench-patches` output, one panel per
scene: uniform sizes (and the source's triangles) as a line, `auto` as stars (the standard
budget, and a third of the best uniform way's patches); bakes solved on pieces (the default)
in colour, bakes solved whole (`--whole`, or files from before pieces) in grey.

    for s in 1 2 3; do
        ./target/release/radiosity bench-patches --seed $s --out docs/patches-seed$s.json
    done
    pip install matplotlib
    python3 docs/plot_patches.py docs/patches.png docs/patches-seed*.json

The README's figure: `python3 docs/plot_patches.py docs/patches.png docs/patches.json
docs/patches-whole.json` (the latter the run before pieces, solved whole).

With several files (seeds), each point is their mean, with a bar from the lowest to the
highest: how much the figure itself moves with the lines and the reference's paths.

`--measure point_error` (first) plots the error at the resolution of points instead (the
README's second figure, `docs/patches-point.png`, from `docs/patches.json` alone); points
without that measure (older files) are left out, and an error below what the reference
resolves (`point_resolution`) is drawn at that resolution under a hollow triangle.
"""
import json
import sys
from statistics import mean

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def key(p):
    return (p["scene"], str(p["patch_size"]), p.get("budget"), p.get("split", False))


LABELS = {
    "patch_error": "per-patch error against the path tracer (%)",
    "point_error": "error at points against the path tracer (%)",
}


def main(target, sources, measure="patch_error"):
    runs = {}
    for source in sources:
        with open(source) as f:
            for p in json.load(f):
                if measure in p:
                    runs.setdefault(key(p), []).append(p)
    scenes = sorted({k[0] for k in runs})
    columns = min(2, len(scenes))
    rows = (len(scenes) + columns - 1) // columns
    fig, axes = plt.subplots(rows, columns, figsize=(6 * columns, 4.5 * rows), squeeze=False)
    for ax in axes.flat[len(scenes):]:
        ax.set_visible(False)
    for ax, scene in zip(axes.flat, scenes):
        bounds = []
        for split in (False, True):
            uniform, auto = [], []
            for k, ps in runs.items():
                if k[0] != scene or k[3] != split:
                    continue
                # The error at points below what the reference resolves: drawn at that
                # resolution, an upper bound (marked below).
                floor = "point_resolution" if measure == "point_error" else None
                errors = [100 * max(p[measure], p.get(floor, 0.0) if floor else 0.0) for p in ps]
                if floor and any(p[measure] < p.get(floor, 0.0) for p in ps):
                    bounds.append((mean(p["patches"] for p in ps), mean(errors)))
                point = (mean(p["patches"] for p in ps), mean(errors), min(errors), max(errors), k)
                (auto if k[1] == "auto" else uniform).append(point)
            if not uniform and not auto:
                continue
            uniform.sort()
            style = {} if split else {"color": "0.6", "linestyle": "--"}
            how = "on pieces" if split else "whole"
            xs = [u[0] for u in uniform]
            ys = [u[1] for u in uniform]
            low = [u[1] - u[2] for u in uniform]
            high = [u[3] - u[1] for u in uniform]
            ax.errorbar(xs, ys, yerr=[low, high], marker="o", capsize=3,
                        label=f"uniform / source, {how}", **style)
            for u in uniform:
                ax.annotate(u[4][1], (u[0], u[1]), textcoords="offset points", xytext=(4, 4),
                            fontsize=8)
            for a in sorted(auto):
                star = {} if split else {"color": "0.6"}
                ax.errorbar([a[0]], [a[1]], yerr=[[a[1] - a[2]], [a[3] - a[1]]], marker="*",
                            markersize=12, capsize=3, linestyle="none",
                            label=f"auto, budget {a[4][2]}, {how}", **star)
        for x, y in bounds:
            ax.plot([x], [y], "v", markersize=14, markerfacecolor="none", color="k")
        if bounds:
            ax.plot([], [], "v", markerfacecolor="none", color="k",
                    label="below what the reference resolves (drawn there)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.yaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("patches")
        ax.set_ylabel(LABELS[measure])
        ax.set_title(scene)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(target, dpi=110)


if __name__ == "__main__":
    args = sys.argv[1:]
    if args[0] == "--measure":
        main(args[2], args[3:], args[1])
    else:
        main(args[0], args[1:])
