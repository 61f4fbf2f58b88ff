"""tools/service_bench.py's live part: the prepared flight, the matching of answers to
samples, the rate sweep's verdict, and a short sweep against the real service.

Timing is the bench's business, not the tests': these check structure and counting.
"""

from __future__ import annotations

import math

import numpy as np
from tool_module import load_tool

from mavest.mavlink.messages import Encoder

bench = load_tool("service_bench")


def test_the_prepared_flight_has_one_imu_packet_per_sample_due_in_time() -> None:
    flight = bench.prepare_flight(0.5, 2000.0)
    assert flight.samples == 1001  # both ends
    assert np.all(np.diff(flight.times) > 0.0)
    imu_groups = flight.keys >= 0
    assert all(bool(flight.imu[i]) == imu_groups[i] for i in range(len(flight.times)))
    # at 2 kHz two samples share each time_boot_ms: the answers are told apart by order
    keys = flight.keys[imu_groups]
    assert np.all(np.diff(keys) >= 0)
    assert np.bincount(keys - keys.min()).max() == 2
    # SIMSTATE (truth) goes with every sample, HEARTBEAT and the rest now and then
    assert all(len(flight.others[i]) >= 1 for i in np.flatnonzero(imu_groups))


def _answer(encoder: Encoder, key: int) -> bytes:
    return encoder.attitude(key, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))


def test_answers_are_matched_by_time_boot_ms_then_in_order() -> None:
    flight = bench.prepare_flight(0.01, 2000.0)
    samples = np.flatnonzero(flight.keys >= 0)
    sent_ns = np.zeros(len(flight.times), dtype=np.int64)
    sent_ns[samples] = 1_000_000_000 + np.arange(len(samples)) * 500_000
    encoder = Encoder(1, 191)
    # every sample answered 0.3 ms after it was sent, except the last, never answered;
    # one ATTITUDE in the same datagram as its ATTITUDE_QUATERNION; one for no sample
    replies = []
    for i in samples[:-1]:
        packet = _answer(encoder, int(flight.keys[i]))
        packet += encoder.attitude_quaternion(
            int(flight.keys[i]), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        )
        replies.append((packet, int(sent_ns[i]) + 300_000))
    replies.append((_answer(encoder, 12345), 2_000_000_000))
    lateness = np.zeros(len(flight.times))
    run = bench._score(flight, sent_ns, lateness, replies, 0)
    assert run.sent == len(samples)
    assert run.answered == len(samples) - 1
    assert run.lost == 1
    assert run.unmatched == 1
    np.testing.assert_allclose(run.latencies, 0.3)
    np.testing.assert_array_equal(run.answered_at, flight.times[samples[:-1]])


def _run(rate: float, lost: int, last_second_ms: float) -> object:
    times = np.linspace(0.0, 3.0, 31)
    latencies = np.where(times >= 2.0, last_second_ms, 0.5)
    return bench.LiveRun(
        rate=rate,
        sent=31 + lost,
        answered=31,
        latencies=latencies,
        answered_at=times,
        lateness=np.zeros(31 + lost),
    )


def test_the_highest_rate_is_the_fastest_without_loss_that_kept_up() -> None:
    runs = [
        _run(1000.0, 0, 0.5),
        _run(2000.0, 0, 0.8),
        _run(4000.0, 0, 2 * bench.KEPT_UP_MS),  # no loss yet, but a backlog growing
        _run(8000.0, 5, 0.5),
    ]
    assert [run.kept_up for run in runs] == [True, True, False, True]
    assert bench.highest_sustained(runs).rate == 2000.0
    assert bench.highest_sustained(runs[2:]) is None


def test_a_short_sweep_against_the_service() -> None:
    rates = [250.0, 500.0]
    runs = bench.rate_sweep(rates, 1.5)
    assert [run.rate for run in runs] == rates
    for run, rate in zip(runs, rates, strict=True):
        assert run.sent == round(1.5 * rate) + 1
        assert 0 < run.answered <= run.sent
        assert len(run.latencies) == run.answered
        assert np.all(run.latencies > 0.0)
        assert run.unmatched == 0
        row = run.row()
        assert row["p50 ms"] <= row["p99 ms"] <= row["max ms"]
        assert math.isfinite(row["service CPU %"])
    best = bench.highest_sustained(runs)
    assert best is None or best.rate in rates


def test_the_pipeline_cost_runs_the_checkout_in_a_fresh_process() -> None:
    flight = bench.prepare_flight(0.5, 200.0)
    costs = bench.pipeline_cost(flight, {"mavest": ""}, rounds=2)
    assert list(costs) == ["mavest"] and len(costs["mavest"]) == 2
    # tens to hundreds of µs per sample: anything else is a unit slip, or no samples
    assert all(5.0 < cost < 5000.0 for cost in costs["mavest"])
