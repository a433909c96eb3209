"""benchmarks/train_generative.py's generation wall time: the sum of the per-bundle times that
benchmarks/make_randomised.py writes beside each bundle, however the streets were made."""

from __future__ import annotations

import json

from benchmarks.make_randomised import GENERATION_FILE
from benchmarks.train_generative import bundle_generation_seconds


def _bundle(root, split, i, seconds=None):
    d = root / split / f"{split}_{i:06d}"
    d.mkdir(parents=True)
    (d / "bundle.json").write_text("{}")
    if seconds is not None:
        (d / GENERATION_FILE).write_text(json.dumps({"seconds": seconds, "workers": 1}))


def test_sums_the_timed_bundles_and_counts_the_untimed(tmp_path):
    _bundle(tmp_path, "train", 0, 40.5)
    _bundle(tmp_path, "train", 1, 59.5)
    _bundle(tmp_path, "train", 2)  # made before the file existed
    _bundle(tmp_path, "val", 0, 12.0)
    (tmp_path / "val" / "val_000001").mkdir()  # unfinished: no bundle.json, not a street
    out = bundle_generation_seconds(tmp_path, ["train", "val", "test_id"])
    assert out["process_s"] == 112.0 and out["bundles_timed"] == 3 and out["untimed"] == 1
    assert out["per_split_process_s"] == {"train": 100.0, "val": 12.0, "test_id": 0.0}
