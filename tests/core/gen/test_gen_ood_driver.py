"""The OOD driver of benchmarks/train_generative.py (issue #18): the validation score and the rule
that decides whether a fine-tuned inverse model replaces the shipped one."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def tg():
    spec = importlib.util.spec_from_file_location("train_generative", REPO / "benchmarks" / "train_generative.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _m(psnr, n, r, mt):
    return {"albedo_si_psnr": psnr, "normal_mae_deg": n, "roughness_rmse": r, "metallic_rmse": mt}


def test_val_score_is_one_at_the_targets_and_orders_models(tg):
    assert tg.val_score(_m(19.0, 12.0, 0.15, 0.10)) == pytest.approx(1.0)
    assert tg.val_score(_m(21.0, 8.0, 0.1, 0.05)) < tg.val_score(_m(15.0, 30.0, 0.3, 0.2))


def test_replace_decision(tg):
    before = {"val": {"score": 2.0}, "old_held_out": {"mean": _m(20.6, 7.0, 0.125, 0.076)}}
    good = {"val": {"score": 1.0}, "old_held_out": {"mean": _m(20.4, 7.5, 0.13, 0.08)}}
    assert tg.replace_decision(before, good)["replace"]
    # better on val but materially worse on the old held-out streets: vetoed
    bad_old = {"val": {"score": 1.0}, "old_held_out": {"mean": _m(19.0, 7.0, 0.125, 0.076)}}
    d = tg.replace_decision(before, bad_old)
    assert d["better_on_val"] and not d["replace"] and d["materially_worse_on_old"]
    # not better on val: kept
    assert not tg.replace_decision(before, {"val": {"score": 2.5}, "old_held_out": before["old_held_out"]})["replace"]
    # better on val, but by less than the margin (the spread of snapshots that change nothing): kept
    close = {"val": {"score": 2.0 - tg.VAL_MARGIN / 2}, "old_held_out": before["old_held_out"]}
    assert tg.VAL_MARGIN > 0 and not tg.replace_decision(before, close)["better_on_val"]
    assert tg.replace_decision(before, {**close, "val": {"score": 2.0 - 2 * tg.VAL_MARGIN}})["replace"]
