"""Inference settings and the uncertainty's scale, chosen on validation labels after training.

A trained network's 2D decoding window (``model.map_window``) and P1's view rejection
(``model.fusion_reject``) act at inference only; which values suit a network depends on
how well it has learned (after few steps a wide window often decodes better). When a run
has validation labels (``[data] validation_labels``), the final checkpoint ``model.pt`` gets
the values with the lowest median P1 error on them: the window first (with the
configured rejection), then the rejection with the chosen window; a value replaces the
configured one only when it lowers the median by more than :data:`MIN_GAIN`. The same
predictions fit the scale of the per-keypoint uncertainty
(:func:`freipose.nn.uncertainty.fit_scale`). ``model.pt`` records what was chosen, on how
many instants and the median error of every value tried (``validation`` in the checkpoint,
:func:`freipose.nn.checkpoint.validation_record`); ``freipose eval`` reports it. The
validation labels must not be the labels the network is finally scored on.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freipose.nn.config import ModelConfig, TrainConfig, config_from_dict
from freipose.nn.data import collate_prepared, prepare_sample
from freipose.nn.inference import predict_prepared
from freipose.nn.types import Batch, SampleSource
from freipose.nn.uncertainty import fit_scale, raw_uncertainty

log = logging.getLogger(__name__)

MAP_WINDOWS = (0, 1, 2, 3, 5, 8)
FUSION_REJECTS = (0.0, 0.5, 1.0, 2.0, 4.0)
MIN_GAIN = 0.01
"""A value replaces the configured one when it lowers the median P1 error by this share."""
MAX_INSTANTS = 256


def _batches(source: SampleSource, model: ModelConfig, batch_size: int = 4) -> list[Batch]:
    """The usable validation instants, cropped around their label centres, collated."""
    from freipose.nn.evaluate import first_pass_sample, usable_indices

    idx = usable_indices(source)
    if len(idx) > MAX_INSTANTS:
        idx = idx[np.linspace(0, len(idx) - 1, MAX_INSTANTS).round().astype(int)]
    # the inputs of a first inference pass (no other animal painted out from the labels)
    prepared = [prepare_sample(first_pass_sample(source[int(i)]), model) for i in idx]
    return [
        collate_prepared(prepared[i : i + batch_size]) for i in range(0, len(prepared), batch_size)
    ]


def _predict(net: torch.nn.Module, batches: list[Batch], cfg: ModelConfig) -> dict[str, Any]:
    """P0, P1, the raw uncertainty and the labels of every batch with ``cfg``'s settings."""
    inner = getattr(net, "module", net)
    kept = inner.cfg
    inner.cfg = cfg
    try:
        preds = [predict_prepared(net, b) for b in batches]
    finally:
        inner.cfg = kept
    gt = np.concatenate([b["points3d"].numpy().astype(np.float64) for b in batches])
    gt[~np.concatenate([b["mask3d"].numpy() for b in batches])] = np.nan
    raw = [
        raw_uncertainty(p["P0"], p["P1"], p["points2d"], p["confidence2d"], b["rigs"],
                        cfg.voxel_size)
        for p, b in zip(preds, batches)
    ]  # fmt: skip
    P1 = np.concatenate([p["P1"] for p in preds])
    return {"P1": P1, "gt": gt, "raw": np.concatenate(raw)}


def _median_error(pred: dict[str, Any]) -> float:
    """Median 3D error (mm) of P1 over the labeled keypoints."""
    e = np.linalg.norm(pred["P1"] - pred["gt"], axis=-1)
    return float(np.nanmedian(e)) if np.isfinite(e).any() else float("inf")


def _best(
    net: torch.nn.Module, batches: list[Batch], cfg: ModelConfig, key: str, values: Sequence[Any]
) -> tuple[ModelConfig, dict[str, float]]:
    """``cfg`` with the value of ``key`` of lowest median error, and the error of each."""
    tried: dict[str, float] = {}
    configured = getattr(cfg, key)
    for v in sorted({*values, configured}):
        tried[str(v)] = _median_error(_predict(net, batches, dataclasses.replace(cfg, **{key: v})))
    best = min(tried, key=tried.__getitem__)
    if tried[best] < tried[str(configured)] * (1.0 - MIN_GAIN):
        cfg = dataclasses.replace(cfg, **{key: type(configured)(float(best))})
    return cfg, tried


def choose_settings(net: torch.nn.Module, source: SampleSource, model: ModelConfig) -> dict:
    """The inference settings and uncertainty scale chosen on validation labels.

    Args:
        net: the trained network (put in eval mode).
        source: the validation samples (with 3D labels).
        model: the network's config.

    Returns:
        The record stored in the checkpoint: ``chosen`` and ``configured`` settings,
        ``tried`` (setting -> value -> median P1 error, mm), ``instants``,
        ``median_p1_mm`` with the chosen settings, ``uncertainty_scale`` and
        ``uncertainty_coverage`` (share within two sigma on these labels). Empty without a
        usable validation instant.
    """
    batches = _batches(source, model)
    if not batches:
        return {}
    net.eval()
    cfg, tried = model, {}
    cfg, tried["map_window"] = _best(net, batches, cfg, "map_window", MAP_WINDOWS)
    if model.kind == "voxel" and model.refine:
        cfg, tried["fusion_reject"] = _best(net, batches, cfg, "fusion_reject", FUSION_REJECTS)
    pred = _predict(net, batches, cfg)
    cal = fit_scale(np.linalg.norm(pred["P1"] - pred["gt"], axis=-1), pred["raw"])
    keys = [k for k in ("map_window", "fusion_reject") if k in tried]
    return {
        "chosen": {k: getattr(cfg, k) for k in keys},
        "configured": {k: getattr(model, k) for k in keys},
        "tried": tried,
        "instants": int(sum(len(b["index"]) for b in batches)),
        "median_p1_mm": _median_error(pred),
        "uncertainty_scale": cal.scale,
        "uncertainty_coverage": cal.coverage,
    }


def validation_source(config: TrainConfig) -> SampleSource | None:
    """The samples of ``[data] validation_labels`` (None without them).

    Videos are relative to ``[data] root``, else to the labels file's folder.

    Raises:
        InputFileError: the labels file does not exist.
        LabelsDataError: a camera of ``[data] cameras`` that the labels do not have.
    """
    from freipose.io.labels import read_labels_h5
    from freipose.nn.dataset import MultiViewDataset

    d = config.data
    if not d.validation_labels:
        return None
    path = Path(d.validation_labels)
    root = Path(d.root) if d.root else path.resolve().parent
    return MultiViewDataset(read_labels_h5(path), root=root, cameras=list(d.cameras) or None)


def with_validation(
    ckpt: dict[str, Any], net: torch.nn.Module, config: TrainConfig
) -> dict[str, Any]:
    """The final checkpoint with the settings chosen on the validation labels.

    Args:
        ckpt: the checkpoint dict (:func:`freipose.nn.checkpoint.training_checkpoint`).
        net: the trained network.
        config: the run's config (``[data] validation_labels``: unchanged without them).

    Returns:
        ``ckpt`` with ``config.model`` holding the chosen settings and ``validation`` the
        record of :func:`choose_settings`.
    """
    source = validation_source(config)
    if source is None:
        return ckpt
    model = config_from_dict(ckpt["config"]).model
    was_training = net.training
    with torch.no_grad():
        record = choose_settings(net, source, model)
    net.train(was_training)
    if not record:
        return ckpt
    log.info("inference settings chosen on %d validation instants: %s (configured %s)",
             record["instants"], record["chosen"], record["configured"])  # fmt: skip
    config = {**ckpt["config"], "model": {**ckpt["config"]["model"], **record["chosen"]}}
    return {**ckpt, "config": config, "validation": record}
