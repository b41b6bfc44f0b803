"""``freipose analyze variables --help`` states the variable counts the code computes."""

from __future__ import annotations

import re

import pytest
from click.testing import CliRunner

from freipose.analysis.signals import stft_frequencies
from freipose.analysis.variables import VariableConfig, variable_layout
from freipose.cli.main import cli
from freipose.demo.presets import PRESETS
from freipose.skeleton import BUILTIN_SKELETONS, load_skeleton


def _help() -> str:
    res = CliRunner().invoke(cli, ["analyze", "variables", "--help"], terminal_width=200)
    assert res.exit_code == 0, res.output
    return re.sub(r"\s+", " ", res.output)


def _count(skeleton: str, window: int) -> int:
    return len(variable_layout(load_skeleton(skeleton), stft_frequencies(window, 25.0)).names)


@pytest.mark.parametrize("name", sorted(BUILTIN_SKELETONS))
def test_variable_formula_in_help_matches_the_layout(name):
    assert "9 + 2F per keypoint and 2 per angle, with F = STFT window / 2 + 1" in _help()
    skel = load_skeleton(name)
    for window in (16, 32, 64):
        f = window // 2 + 1
        assert _count(name, window) == len(skel.keypoints) * (9 + 2 * f) + 2 * len(skel.angles)


def test_rat_counts_in_help_are_the_computed_ones():
    text = _help()
    pattern = (r"The (\d+)-keypoint rat with (\d+) angles has (\d+) at the default "
               r"(\d+)-frame window and (\d+) at (\d+) frames \(freipose demo\)")  # fmt: skip
    m = re.search(pattern, text)
    assert m, text
    k, a, n_default, default, n_demo, demo = map(int, m.groups())
    rat = load_skeleton("rat")
    assert (k, a) == (len(rat.keypoints), len(rat.angles))
    assert default == VariableConfig().stft_window and f"[default: {default};" in text
    assert n_default == _count("rat", default)
    assert demo == PRESETS["small"].stft_window and n_demo == _count("rat", demo)
