"""Figures of the attribution analysis (PNG, made without pyplot).

- ``attribution_<animal>_<condition>.png``: F-score heat maps by body part (rows) and
  variable type (columns), one panel per variable family, dots where significant
  (method Figure 5.6b);
- ``classifier_response.png``: the full classifier's mean prediction aligned to stimulation
  onset, one panel per group, one line per evaluated animal (Figure 5.6a);
- ``top_variables_<animal>_<condition>.png``: time courses (z-scored) of the best variables
  around onset.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from freipose.io.figures import new_figure, save_figure

PANELS = (
    (
        "position, distance and velocity",
        ("local", "local_vel", "origin_dist", "origin_dist_vel", "floor_dist"),
    ),
    ("STFT of distance to body origin (Hz)", ("origin_dist_stft",)),
    ("STFT of distance to floor (Hz)", ("floor_dist_stft",)),
    ("angles", ("angle", "angle_vel")),
)


def safe_name(text: str) -> str:
    """A file-name-safe version of an animal or condition name.

    Args:
        text: the name.

    Returns:
        The name with every run of characters other than letters, digits, ``_``, ``.`` and
        ``-`` replaced by ``_`` (``x`` when nothing is left).
    """
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "x"


def attribution_heatmap(
    att: pd.DataFrame, kinds: dict[str, str], path: str | Path, title: str
) -> None:
    """Heat map of single-variable F-scores of one group.

    Args:
        att: attribution rows of one group (columns variable, f1, significant, type, part).
        kinds: variable -> kind, in the variables' file order (panels, row and column order).
        path: output PNG.
        title: figure title.
    """
    order = {name: i for i, name in enumerate(kinds)}
    att = att.assign(kind=att["variable"].map(kinds), _order=att["variable"].map(order))
    att = att.sort_values("_order", kind="stable")
    panels = []
    for label, ks in PANELS:
        sub = att[att["kind"].isin(ks)]
        if len(sub):
            panels.append((label, sub))
    # Keep the file order of types and parts.
    widths = [max(4, sub["type"].nunique()) for _, sub in panels]
    heights = [sub["part"].nunique() for _, sub in panels]
    fig_w = min(26, 3 + 0.28 * sum(widths))
    fig_h = 2.2 + 0.32 * max(heights)
    # constrained layout leaves room for each panel's own row labels (no overlaps)
    fig = new_figure((fig_w, fig_h), layout="constrained")
    axes = fig.subplots(1, len(panels), gridspec_kw={"width_ratios": widths}, squeeze=False)
    finite = att["f1"].to_numpy(dtype=float)
    finite = finite[np.isfinite(finite)]
    vmin = 0.0 if not len(finite) else max(0.0, min(0.5, float(finite.min())))
    im = None
    prev_parts: list[str] = []
    for ax, (label, sub) in zip(axes[0], panels):
        types = list(dict.fromkeys(sub["type"]))
        parts = list(dict.fromkeys(sub["part"]))
        grid = np.full((len(parts), len(types)), np.nan)
        sig = np.zeros_like(grid, dtype=bool)
        ti = {t: i for i, t in enumerate(types)}
        pi = {p: i for i, p in enumerate(parts)}
        for t, p, f, s in zip(sub["type"], sub["part"], sub["f1"], sub["significant"]):
            grid[pi[p], ti[t]] = f
            sig[pi[p], ti[t]] = bool(s)
        im = ax.imshow(
            grid, aspect="auto", cmap="viridis", vmin=vmin, vmax=1.0, interpolation="nearest"
        )
        yy, xx = np.nonzero(sig)
        ax.scatter(xx, yy, s=14, c="white", edgecolors="black", linewidths=0.4, zorder=3)
        kind0 = sub["kind"].iloc[0]
        if kind0.endswith("_stft"):
            xt = [t.rsplit("_", 1)[-1].removesuffix("Hz") for t in types]
            step = max(1, len(xt) // 11)
            ax.set_xticks(range(0, len(xt), step))
            ax.set_xticklabels(xt[::step], rotation=90, fontsize=8)
        else:
            ax.set_xticks(range(len(types)))
            ax.set_xticklabels(types, rotation=90, fontsize=8)
        ax.set_yticks(range(len(parts)))
        ax.set_yticklabels(parts if parts != prev_parts else [], fontsize=8)
        prev_parts = parts
        ax.set_title(label, fontsize=9)
    fig.suptitle(title + "  (F-score; dots: significant)", fontsize=10)
    if im is not None:
        fig.colorbar(im, ax=list(axes[0]), fraction=0.02, pad=0.01, label="F-score (macro)",
                     shrink=0.9)  # fmt: skip
    save_figure(fig, Path(path), dpi=110, bbox_inches="tight")


def classifier_response(dyn: pd.DataFrame, path: str | Path) -> None:
    """Onset-aligned mean prediction of the full classifier, one panel per group.

    Args:
        dyn: ``dynamics.csv`` rows of all groups.
        path: output PNG.
    """
    groups = list(dict.fromkeys(zip(dyn["animal"], dyn["condition"])))
    n = max(1, len(groups))
    cols = min(3, n)
    rows = int(np.ceil(n / cols))
    fig = new_figure((4.6 * cols, 3.2 * rows))
    axes = fig.subplots(rows, cols, squeeze=False, sharey=True)
    for ax, (animal, cond) in zip(axes.flat, groups):
        g = dyn[(dyn["animal"] == animal) & (dyn["condition"] == cond)]
        first = g[g["evaluated_on"] == g["evaluated_on"].iloc[0]]
        t = first["time_s"].to_numpy()
        stim = first["stimulated_fraction"].to_numpy()
        ax.fill_between(
            t, 0, 1, where=stim > 0.5, color="0.75", alpha=0.5, lw=0, label="stimulation"
        )
        for target, d in g.groupby("evaluated_on", sort=False):
            m = d["mean_prediction"].to_numpy(dtype=float)
            s = d["sem_prediction"].to_numpy(dtype=float)
            own = target == animal
            (line,) = ax.plot(
                d["time_s"], m, lw=1.6 if own else 1.0, label=f"{target}{' (own)' if own else ''}"
            )
            ax.fill_between(
                d["time_s"],
                m - np.nan_to_num(s),
                m + np.nan_to_num(s),
                color=line.get_color(),
                alpha=0.2,
                lw=0,
            )
        ax.axvline(0, color="k", lw=0.6)
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(f"trained on {animal}, {cond}", fontsize=9)
        ax.set_xlabel("time from stimulation onset (s)")
        ax.legend(fontsize=7, loc="upper right")
    for ax in axes[:, 0]:
        ax.set_ylabel("mean predicted 'stimulated'")
    for ax in list(axes.flat)[len(groups) :]:
        ax.set_visible(False)
    fig.suptitle("Full classifier on held-out recordings, aligned to onset", fontsize=10)
    fig.tight_layout()
    save_figure(fig, Path(path), dpi=110, bbox_inches="tight")


def top_variables(tc: pd.DataFrame, dyn: pd.DataFrame, path: str | Path, title: str) -> None:
    """Time courses of the top variables of one group (z-scored with train statistics).

    Args:
        tc: ``top_variables.csv`` rows of the group.
        dyn: ``dynamics.csv`` rows of the group's classifier on its own animal (the
            stimulation is shaded where most trials are stimulated).
        path: output PNG.
        title: figure title.
    """
    fig = new_figure((9.5, 4.2))
    ax = fig.subplots()
    if len(dyn):
        t = dyn["time_s"].to_numpy()
        stim = dyn["stimulated_fraction"].to_numpy()
        ax.axvspan(
            float(t[stim > 0.5].min()) if (stim > 0.5).any() else 0.0,
            float(t[stim > 0.5].max()) if (stim > 0.5).any() else 0.0,
            color="0.75",
            alpha=0.5,
            lw=0,
            label="stimulation",
        )
    for (vname, rank), d in tc.groupby(["variable", "rank"], sort=False):
        m = d["mean_z"].to_numpy(dtype=float)
        s = np.nan_to_num(d["sem_z"].to_numpy(dtype=float))
        (line,) = ax.plot(d["time_s"], m, lw=1.2, label=f"{rank}. {vname}")
        ax.fill_between(d["time_s"], m - s, m + s, color=line.get_color(), alpha=0.15, lw=0)
    ax.axvline(0, color="k", lw=0.6)
    ax.set_xlabel("time from stimulation onset (s)")
    ax.set_ylabel("z-score (train mean/std)")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8.5, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    save_figure(fig, Path(path), dpi=110, bbox_inches="tight")


def power_curves(table: pd.DataFrame, target: float, path: str | Path, title: str) -> None:
    """Power against trials per animal, one line per number of animals (``design.csv``).

    Args:
        table: rows of :func:`freipose.analysis.design.power_table`.
        target: the power wanted (a dashed line).
        path: output PNG.
        title: figure title.
    """
    fig = new_figure((5.6, 3.8))
    ax = fig.subplots()
    for animals, g in table.groupby("animals", sort=True):
        line = ax.plot(g["trials"], g["power"], marker="o", lw=1.4,
                       label=f"{animals} animal{'s' if animals != 1 else ''}")[0]  # fmt: skip
        ax.fill_between(g["trials"], g["power_low"], g["power_high"], color=line.get_color(),
                        alpha=0.2, lw=0)  # fmt: skip
    ax.axhline(target, color="k", ls="--", lw=0.8, label=f"target {target:g}")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("stimulation trials per animal (half train, half test)")
    ax.set_ylabel("power: significant in every animal")
    ax.set_ylim(-0.02, 1.02)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    save_figure(fig, Path(path), dpi=110, bbox_inches="tight")
