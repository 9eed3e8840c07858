"""The run's messages (synth/progress.py): durations, the progress line and the last line."""

from __future__ import annotations

import math

from synth.progress import Progress, hms


def test_durations_read_as_minutes_or_hours():
    assert hms(0) == "0m00s" and hms(61.9) == "1m01s" and hms(3 * 3600 + 125) == "3h02m"
    assert hms(math.nan) == hms(math.inf) == "--"


def test_the_meter_counts_images_and_ends_with_the_manifests_totals(capsys):
    meter = Progress(4, enabled=False)
    for _ in range(3):
        meter.tick()
    assert meter.made == 3 and meter.line().startswith("3/4 images (75 %)")
    meter.done({"shards": {"a": {"samples": 2}, "b": {"samples": 1}}, "skipped": [{"index": 3}]})
    err = capsys.readouterr().err
    assert err.startswith("[synth] done: 3 samples in 2 shards, ") and err.rstrip().endswith(", 1 skipped")
