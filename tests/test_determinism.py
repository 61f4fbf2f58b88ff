"""Results do not depend on numba's disk cache: a replay that compiles the filter and the
next one, which loads it from the cache, write the same bytes (with numba's internals or
its public interface only, whichever ``MAVEST_NUMBA_PUBLIC`` selects)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog


def test_a_replay_compiled_and_one_loaded_from_the_cache_write_the_same_bytes(
    tmp_path: Path,
) -> None:
    flight = tmp_path / "flight.tlog"
    # (long enough to reach the magnetometer's and the iterated updates' less common
    # branches, where kernels fused differently once diverged)
    write_flight_tlog(flight, 20.0, 200.0, AUTOPILOTS["ardupilot"], seed=1)
    cache = tmp_path / "cache"
    env = dict(os.environ, MAVEST_CACHE_DIR=str(cache))
    written: list[bytes] = []
    cached: list[dict[Path, int]] = []
    for name in ("compiled", "loaded"):
        out = tmp_path / f"{name}.tlog"
        command = [sys.executable, "-m", "mavest", "replay", str(flight), "--out-tlog", str(out)]
        subprocess.run([*command, "-q"], env=env, capture_output=True, check=True)
        written.append(out.read_bytes())
        cached.append({path: path.stat().st_mtime_ns for path in cache.rglob("*.nb[ic]")})
    # compiled into an empty cache, then loaded from it (a compile rewrites an index)
    assert cached[0] and cached[1] == cached[0]
    assert len(written[0]) > 400_000 and written[1] == written[0]
