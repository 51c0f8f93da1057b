"""The time-to-quality benchmark's pure functions (bench/quality_ladder.py): time to an error along
a ladder, the reference cache key, the tone map. Plain Python, no bpy."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import quality_ladder as ql  # noqa: E402

# --- time_to_error ---------------------------------------------------------------------------------


def test_interpolates_a_power_law_exactly_in_log_log():
    # error = 0.4 * t^-0.5: the crossing of 0.1 is at t = 16, between the rungs at 4 s and 64 s.
    points = [(1.0, 0.4), (4.0, 0.2), (64.0, 0.05)]
    got = ql.time_to_error(points, 0.1)
    assert got.how == "interpolated"
    assert got.seconds == pytest.approx(16.0, rel=1e-12)


def test_a_rung_exactly_at_the_target_is_its_own_time():
    got = ql.time_to_error([(1.0, 0.3), (2.0, 0.2), (8.0, 0.1)], 0.2)
    assert got.seconds == pytest.approx(2.0)


def test_order_of_the_points_does_not_matter_and_the_first_crossing_wins():
    # Noise makes ladders non-monotone: 3 s already reaches 0.1, 5 s falls back above it.
    points = [(5.0, 0.12), (1.0, 0.5), (3.0, 0.1), (9.0, 0.05)]
    assert ql.time_to_error(points, 0.1).seconds == pytest.approx(3.0)
    # Between 1 s (0.5) and 3 s (0.1): 0.2 is reached at 1 * 3^(log(0.4)/log(0.2)).
    expected = 3.0 ** (math.log(0.2 / 0.5) / math.log(0.1 / 0.5))
    assert ql.time_to_error(points, 0.2).seconds == pytest.approx(expected)


def test_cheapest_rung_below_target_is_an_upper_bound():
    got = ql.time_to_error([(2.0, 0.01), (4.0, 0.005)], 0.1)
    assert got.how == "at_most" and got.seconds == 2.0


def test_never_reaching_the_target_is_infinite_with_a_reason():
    got = ql.time_to_error([(1.0, 0.3), (10.0, 0.2)], 0.1)
    assert math.isinf(got.seconds) and got.how == "never"
    assert "0.2" in got.reason
    assert got.as_json()["seconds"] is None  # JSON cannot carry inf


def test_unusable_points_are_skipped():
    points = [(0.0, 0.1), (1.0, None), (2.0, float("nan")), (4.0, 0.4), (8.0, 0.1)]
    assert ql.time_to_error(points, 0.1).seconds == pytest.approx(8.0)
    assert ql.time_to_error([], 0.1).how == "never"


def test_crossing_rungs_are_the_ones_the_time_reads():
    points = [(5.0, 0.12), (1.0, 0.5), (3.0, 0.1), (9.0, 0.05), (0.5, None)]
    # The first crossing in time order is 1 s -> 3 s; the 5 s and 9 s rungs do not enter it.
    assert ql.crossing_rungs(points, 0.2) == (1, 2)
    assert ql.crossing_rungs(points, 0.15) == (1, 2)
    assert ql.crossing_rungs(points, 0.6) == (1,)  # the cheapest rung alone bounds it
    assert ql.crossing_rungs(points, 0.01) == ()  # never
    assert ql.crossing_rungs(points, 0.05) == (3,)  # a rung exactly at the target is its own time
    # Re-timing those rungs moves the result; re-timing the others cannot.
    before = ql.time_to_error(points, 0.2).seconds
    slower_elsewhere = [(50.0, 0.12), (1.0, 0.5), (3.0, 0.1), (90.0, 0.05)]
    assert ql.time_to_error(slower_elsewhere, 0.2).seconds == pytest.approx(before)


def test_speed_ratio():
    fast = ql.TimeToError(1.0, "interpolated")
    slow = ql.TimeToError(4.0, "interpolated")
    never = ql.TimeToError(math.inf, "never", "x")
    assert ql.speed_ratio(fast, slow) == pytest.approx(0.25)
    assert math.isinf(ql.speed_ratio(never, slow))
    assert ql.speed_ratio(fast, never) is None


# --- the reference cache key -----------------------------------------------------------------------

SETTINGS = {"device": "CPU", "max_bounces": 32, "sample_clamp_indirect": 0.0}


def test_reference_key_is_stable_and_follows_every_input():
    base = ql.reference_key("abc", "5.0.1", (640, 360), 1024, SETTINGS)
    assert base == ql.reference_key("abc", "5.0.1", [640, 360], 1024, dict(reversed(list(SETTINGS.items()))))
    assert len(base) == 24 and int(base, 16) >= 0
    others = {
        ql.reference_key("abd", "5.0.1", (640, 360), 1024, SETTINGS),
        ql.reference_key("abc", "5.1.0", (640, 360), 1024, SETTINGS),
        ql.reference_key("abc", "5.0.1", (1280, 720), 1024, SETTINGS),
        ql.reference_key("abc", "5.0.1", (640, 360), 2048, SETTINGS),
        ql.reference_key("abc", "5.0.1", (640, 360), 1024, {**SETTINGS, "max_bounces": 4}),
    }
    assert base not in others and len(others) == 5


def test_scene_digest_of_procedural_scenes_ignores_the_build(tmp_path):
    src = tmp_path / "procedural.py"
    src.write_text("def cornell(): ...\n")
    a, b = tmp_path / "a" / "cornell.blend", tmp_path / "b" / "cornell.blend"
    for path, payload in ((a, b"build one"), (b, b"build two")):
        path.parent.mkdir()
        path.write_bytes(payload)
    # Two builds of the same procedural scene share a key; another scene or source does not.
    assert ql.scene_digest(a, [src]) == ql.scene_digest(b, [src])
    assert ql.scene_digest(a) != ql.scene_digest(b)  # without sources: the bytes
    other = tmp_path / "atrium.blend"
    other.write_bytes(b"build one")
    assert ql.scene_digest(other, [src]) != ql.scene_digest(a, [src])
    before = ql.scene_digest(a, [src])
    src.write_text("def cornell(): return 1\n")
    assert ql.scene_digest(a, [src]) != before


# --- tone map ------------------------------------------------------------------------------------------


def test_tone_map_maps_white_to_one_and_is_monotone():
    x = np.linspace(0.0, 4.0, 50)[:, None, None] * np.ones((1, 1, 3))
    y = ql.tone_map(x, white=2.0)
    assert y.dtype == np.float32 and y.min() >= 0.0 and y.max() <= 1.0
    assert np.all(np.diff(y[:, 0, 0]) >= 0)
    assert ql.tone_map(np.full((1, 1, 3), 2.0), 2.0)[0, 0, 0] == pytest.approx(1.0)
    assert ql.tone_map(np.full((1, 1, 3), np.nan), 1.0)[0, 0, 0] == 0.0


def test_exposure_white_uses_the_masked_percentile():
    img = np.zeros((10, 10, 3))
    img[:5] = 1.0
    img[5:] = 100.0
    mask = np.zeros((10, 10), bool)
    mask[:5] = True
    assert ql.exposure_white(img, mask) == pytest.approx(1.0)
    assert ql.exposure_white(np.zeros((2, 2, 3))) == 1.0  # black: a usable white anyway


def test_retime_renders_the_crossing_rungs_again_and_keeps_each_ones_fastest(monkeypatch, tmp_path):
    """`time_to_quality.retime`: only the renders the times to the target read run again, the
    peers alternating, and each keeps its fastest wall and -gpu seconds (errors stay)."""
    import types

    import time_to_quality as ttq

    target = 0.02
    peers = {
        "cycles_oidn": [{"setting": f"{spp} spp", "spp": spp, "seconds": s, "wall_seconds": s + 1, "combined": e}
                        for spp, s, e in ((1, 2.0, 0.04), (4, 3.0, 0.03), (16, 6.0, target), (64, 15.0, 0.015))],
        "hybridgi": [{"setting": name, "set": [name], "seconds": s, "wall_seconds": s + 1, "seconds_minus_gpu": s - 0.5,
                      "combined": e}
                     for name, s, e in (("a", 1.0, 0.03), ("b", 2.0, 0.025), ("c", 3.0, 0.018), ("d", 9.0, 0.012))],
    }
    calls = []
    runs = {"16": [5.0, 7.0], "b": [1.5, 2.5], "c": [3.5, 2.6]}

    def fake(job, args, tag, engine, samples=None, settings=(), timeout=None):
        key = str(samples) if engine == "CYCLES" else settings[0]
        calls.append(key)
        s = runs[key].pop(0)
        return {"seconds": s, "wall_seconds": s + 1, "steps_ms": {"gbuffer": 400.0}}

    monkeypatch.setattr(ttq, "measured_render", fake)
    args = types.SimpleNamespace(repeat=3, out=tmp_path)
    ttq.retime(types.SimpleNamespace(label="x", slug="x"), args, peers)
    assert calls == ["16", "b", "c", "16", "b", "c"]  # rounds alternate the peers; a, d and 1/4/64 spp never
    cycles16 = peers["cycles_oidn"][2]
    assert cycles16["seconds"] == 5.0 and cycles16["seconds_runs"] == [6.0, 5.0, 7.0]
    b, c = peers["hybridgi"][1], peers["hybridgi"][2]
    assert b["seconds"] == 1.5 and b["seconds_minus_gpu"] == pytest.approx(1.1)
    assert c["seconds"] == 2.6 and c["seconds_minus_gpu"] == pytest.approx(2.2)
    assert c["combined"] == 0.018  # the error is the first run's
    assert peers["hybridgi"][0]["seconds"] == 1.0 and "seconds_runs" not in peers["hybridgi"][0]
