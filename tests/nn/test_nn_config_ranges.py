"""Every number of a training config is checked when it is read, and ``--init`` paths."""

from __future__ import annotations

import dataclasses
import math

import pytest
from click.testing import CliRunner

from freipose.detect.ranges import DETECTOR_RANGES
from freipose.detect.train import DetectorTrainConfig, DetectorTrainError
from freipose.nn.config import (
    AugmentConfig,
    ConfigError,
    ModelConfig,
    ScheduleConfig,
    config_from_dict,
)
from freipose.nn.config_ranges import AUGMENT_RANGES, MODEL_RANGES, SCHEDULE_RANGES


def _float_fields(cls):
    return {
        f.name
        for f in dataclasses.fields(cls)
        if isinstance(f.default, float)
        or (isinstance(f.default, tuple) and f.default and isinstance(f.default[0], float))
    }


@pytest.mark.parametrize(
    "cls, ranges",
    [
        (ModelConfig, MODEL_RANGES),
        (ScheduleConfig, SCHEDULE_RANGES),
        (AugmentConfig, AUGMENT_RANGES),
        (DetectorTrainConfig, DETECTOR_RANGES),
    ],
)
def test_every_float_has_a_range_holding_its_default(cls, ranges):
    assert _float_fields(cls) == set(ranges)
    cls()  # the defaults are inside
    for name, (low, high, _) in ranges.items():
        assert math.isfinite(low) and math.isfinite(high) and low <= high, name


@pytest.mark.parametrize(
    "table, key, value",
    [
        ("schedule", "lr", math.nan),
        ("schedule", "lr", math.inf),
        ("schedule", "lr", 1e6),
        ("schedule", "weight_p0", math.nan),
        ("schedule", "lr_decay", -1.0),
        ("model", "cube_size", math.inf),
        ("model", "map_sigma", 0.0),
        ("augment", "center_jitter", math.nan),
        ("augment", "zoom", [0.9, math.inf]),
    ],
)
def test_bad_numbers_are_refused_naming_key_value_and_range(table, key, value):
    data = {"model": {"preset": "tiny"}}
    data.setdefault(table, {})[key] = value
    with pytest.raises(ConfigError, match=rf"{table}\.{key} must be in \[[-0-9.e]+, [0-9.e]+\]"):
        config_from_dict(data)
    with pytest.raises(ConfigError, match=r"got \[?(nan|inf|1000000|-1|0)"):
        config_from_dict(data)


def test_presets_pass_and_zoom_order():
    for preset in ("tiny", "small", "paper"):
        config_from_dict({"model": {"preset": preset}})
    with pytest.raises(ConfigError, match=r"augment.zoom must be \[min, max\]"):
        config_from_dict({"augment": {"zoom": [1.2, 0.9]}})


@pytest.mark.parametrize(
    "key, value", [("lr", math.nan), ("lr", 1e6), ("hflip", math.inf), ("cube_size", math.inf)]
)
def test_detector_numbers_are_refused(key, value):
    with pytest.raises(DetectorTrainError, match=rf"detector\.{key} must be in \["):
        DetectorTrainConfig.from_dict({key: value})
    with pytest.raises(DetectorTrainError, match=r"detector\.scale must be in"):
        DetectorTrainConfig.from_dict({"scale": [0.7, math.nan]})


@pytest.mark.parametrize("stage", ["pose", "detector"])
def test_bad_number_leaves_no_run_folder(tmp_path, stage):
    from freipose.cli.main import cli

    cfg = tmp_path / "tiny.toml"
    table = "schedule" if stage == "pose" else "detector"
    cfg.write_text(f'[data]\nlabels = "labels.h5"\n[model]\npreset = "tiny"\n[{table}]\nlr = nan\n')
    out = tmp_path / "run"
    r = CliRunner().invoke(cli, ["train", str(cfg), "--stage", stage, "--out", str(out)])
    assert r.exit_code != 0 and f"{table}.lr must be in [1e-12, 1]" in r.output, r.output
    assert "got nan" in r.output and "Traceback" not in r.output
    assert not out.exists()


def test_init_on_the_command_line_is_relative_to_the_current_folder(tmp_path, monkeypatch):
    from freipose.cli.main import cli
    from freipose.nn import train as train_module

    (tmp_path / "L2").mkdir()
    (tmp_path / "L2" / "good.pt").write_bytes(b"the config folder's file")
    cfg = tmp_path / "L2" / "tiny.toml"
    cfg.write_text('[data]\nlabels = "labels.h5"\n[model]\npreset = "tiny"\n')
    here = tmp_path / "L1"
    here.mkdir()
    monkeypatch.chdir(here)
    seen = {}
    monkeypatch.setattr(
        train_module, "train_from_config", lambda *a, **k: seen.setdefault("init", k["init"])
    )
    r = CliRunner().invoke(cli, ["train", "../L2/tiny.toml", "--init", "good.pt"])
    assert r.exit_code != 0 and "--init good.pt: no such checkpoint file" in r.output, r.output
    assert str(here) in r.output and not seen
    (here / "good.pt").write_bytes(b"this folder's file")
    r = CliRunner().invoke(cli, ["train", "../L2/tiny.toml", "--init", "good.pt"])
    assert r.exit_code == 0, r.output
    assert seen["init"] == str((here / "good.pt").resolve())
    seen.clear()
    r = CliRunner().invoke(cli, ["train", "../L2/tiny.toml", "--init", "scratch"])
    assert r.exit_code == 0 and seen["init"] == "scratch"
