"""benchmarks/train_base.py: the base models' training sessions and command line."""

from __future__ import annotations

from collections import Counter

import pytest

BENCHMARK = "train_base"  # the script the conftest fixture ``bench`` loads


def _stim(bench, index: int):
    return bench.scene_config(bench.SEED_START + index, index, 100, 5.0).stimulation


def test_the_first_sessions_stimulate_every_other_one_in_turn(bench):
    firsts = [_stim(bench, i) for i in range(bench.FIRST_MOVING)]
    assert all(s is None for s in firsts[0::2])
    moved = [(s.body_part, s.effect) for s in firsts[1::2]]
    assert moved[:3] == [
        ("Paw Front Right", "oscillate"),
        ("Paw Front Left", "lift"),
        ("Paw Back Right", "freeze"),
    ]


def test_later_sessions_mostly_move_a_paw_and_are_fixed_by_their_seed(bench):
    later = range(bench.FIRST_MOVING, bench.FIRST_MOVING + 64)
    stims = [_stim(bench, i) for i in later]
    assert [s is None for s in stims] == [i % 4 == 0 for i in later]
    parts = Counter(s.body_part for s in stims if s is not None)
    assert set(parts) <= set(bench.MOVED_PARTS)
    front = parts["Paw Front Right"] + parts["Paw Front Left"]
    assert front > sum(parts.values()) / 3
    moving = sum(s.effect in ("oscillate", "lift") for s in stims if s is not None)
    assert moving >= 0.75 * sum(parts.values())
    assert stims == [_stim(bench, i) for i in later]


def test_held_out_sessions_are_not_training_sessions(bench):
    args = bench._parser().parse_args(["--sessions", "48"])
    assert bench.SEED_START + args.sessions - 1 < bench.HELD_OUT_SEED_START


def test_unknown_network_names_are_refused(bench, tmp_path):
    with pytest.raises(SystemExit, match="--networks"):
        bench.main(["--work", str(tmp_path), "--networks", "voxel,unet", "--export-only"])
