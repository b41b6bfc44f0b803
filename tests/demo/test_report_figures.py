"""The report's figures are laid out to be read: no overlapping labels, one row per keypoint."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg

from freipose.analysis import figures
from freipose.demo.steps import calibrate
from freipose.nn.evaluate import write_report


def _capture(monkeypatch, module, name):
    """Replace ``module.name`` (a save function) by one that keeps the figure."""
    kept = []
    monkeypatch.setattr(module, name, lambda fig, *a, **k: kept.append(fig))
    return kept


def _boxes(fig, texts):
    FigureCanvasAgg(fig)
    r = fig.canvas.get_renderer()
    fig.draw(r)
    return [t.get_window_extent(r) for t in texts if t.get_text() and t.get_visible()]


def test_jpe_boxplot_has_one_row_per_keypoint(tmp_path):
    keypoints = [f"keypoint {i}" for i in range(12)]
    rng = np.random.default_rng(0)
    results = {n: np.abs(rng.normal(20, 8, (30, 12))) for n in ("voxel_P0", "voxel_P1")}
    write_report(tmp_path, results, keypoints)
    img = cv2.imread(str(tmp_path / "jpe_boxplot.png"))
    h, w = img.shape[:2]
    assert w <= 1200 and h > 0.6 * w  # tall: keypoints stacked, not a 3888 px wide strip


def test_attribution_heatmap_row_labels_do_not_overlap_other_panels(monkeypatch, tmp_path):
    kept = _capture(monkeypatch, figures, "save_figure")
    rows, kinds = [], {}
    for part in ("Ear Right", "Paw Front Right", "Tail"):
        for t, kind in (("local_x", "local"), ("floor_dist_stft_2Hz", "floor_dist_stft")):
            rows.append((f"{t}[{part}]", t, part, kind))
    for part in ("body_elevation", "head_elevation"):
        rows.append((f"angle[{part}]", "angle", part, "angle"))
    for v, _, _, kind in rows:
        kinds[v] = kind
    att = pd.DataFrame({"variable": [r[0] for r in rows], "type": [r[1] for r in rows],
                        "part": [r[2] for r in rows], "f1": np.linspace(0.4, 0.7, len(rows)),
                        "significant": False})  # fmt: skip
    figures.attribution_heatmap(att, kinds, tmp_path / "a.png", "Attribution")
    (fig,) = kept
    axes = [a for a in fig.axes if a.get_label() != "<colorbar>"]
    FigureCanvasAgg(fig)
    r = fig.canvas.get_renderer()
    fig.draw(r)
    for i, ax in enumerate(axes[1:], start=1):
        left = axes[i - 1].get_window_extent(r)
        for label in _boxes(fig, ax.get_yticklabels()):
            assert label.x0 >= left.x1 - 1, (ax.get_title(), label, left)


def test_calibration_comparison_title_clear_of_panel_titles(monkeypatch, tmp_path):
    kept = _capture(monkeypatch, calibrate, "save_png")
    err = {"cameras": ["cam0", "cam1"], "center_mm": [0.4, 1.3], "rotation_deg": [0.08, 0.07],
           "focal_percent": [[0.3, 0.3], [-0.2, -0.2]]}  # fmt: skip
    calibrate._plot_comparison(err, tmp_path / "c.png")
    (fig,) = kept
    (sup,) = _boxes(fig, [fig._suptitle])
    for ax in fig.axes:
        (title,) = _boxes(fig, [ax.title])
        assert not sup.overlaps(title), ax.get_title()


def test_training_log_plot_names_its_curves_and_units(monkeypatch, tmp_path):
    from freipose.nn import train_log

    kept = _capture(monkeypatch, train_log, "save_figure")
    rows = [{"step": s, "loss": 5.0 / s, "p0": 2.0 / s, "val_jpe_p0": 30.0 - s,
             "val_jpe_p1": 28.0 - s} for s in (1, 2, 3)]  # fmt: skip
    train_log.write_log(tmp_path / "log.csv", rows)
    train_log.plot_log(tmp_path / "log.csv", tmp_path / "log.png")
    (fig,) = kept
    losses, val = fig.axes
    assert losses.get_ylabel() == "loss (log scale)"
    assert [t.get_text() for t in val.get_legend().get_texts()] == ["P0 (3D network)",
                                                                    "P1 (refined)"]  # fmt: skip
    assert val.get_ylabel() == "median JPE (mm)"


def test_baseline_log_plot_has_one_validation_curve(monkeypatch, tmp_path):
    from freipose.nn import train_log

    kept = _capture(monkeypatch, train_log, "save_figure")
    # the baseline's log repeats its one estimate under both validation columns
    rows = [{"step": s, "loss": 5.0 / s, "2d": 2.0 / s, "val_jpe_p0": 30.0 - s,
             "val_jpe_p1": 30.0 - s} for s in (1, 2, 3)]  # fmt: skip
    train_log.write_log(tmp_path / "log.csv", rows)
    train_log.plot_log(tmp_path / "log.csv", tmp_path / "log.png", "baseline")
    (fig,) = kept
    val = fig.axes[1]
    assert len(val.get_lines()) == 1
    assert [t.get_text() for t in val.get_legend().get_texts()] == ["triangulated 2D keypoints"]
