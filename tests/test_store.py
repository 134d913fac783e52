"""Map store: atomic checkpoints, fallback to the previous one, SIGKILL never corrupts."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from cgamap.daemon.store import CheckpointStore, decode_checkpoint


def payload(i: int, n: int = 50) -> dict:
    rng = np.random.default_rng(i)
    return {"i": i, "pose": [float(i), 0.0, 0.1], "map2d": {"segments": rng.normal(size=(n, 4))}}


def test_round_trip_with_arrays(tmp_path):
    store = CheckpointStore(tmp_path)
    p = payload(3)
    store.save(p)
    got = CheckpointStore(tmp_path).load()
    assert got["i"] == 3
    np.testing.assert_array_equal(got["map2d"]["segments"], p["map2d"]["segments"])


def test_previous_kept_and_used_when_current_corrupt(tmp_path, caplog):
    store = CheckpointStore(tmp_path)
    store.save(payload(1))
    store.save(payload(2))
    assert decode_checkpoint(store.previous.read_bytes())["i"] == 1
    data = bytearray(store.current.read_bytes())
    data[len(data) // 2] ^= 0x55  # one flipped bit in the payload
    store.current.write_bytes(bytes(data))
    fresh = CheckpointStore(tmp_path)
    assert fresh.load()["i"] == 1
    assert "unusable" in caplog.text
    fresh.save(payload(3))  # the corrupt one must not push the good one out
    assert decode_checkpoint(fresh.previous.read_bytes())["i"] == 1


def test_truncated_and_missing(tmp_path):
    store = CheckpointStore(tmp_path)
    assert store.load() is None
    store.save(payload(1))
    store.current.write_bytes(store.current.read_bytes()[:40])
    assert store.load() is None  # no previous: start empty rather than crash


KILLER = textwrap.dedent("""
    import sys, numpy as np
    from cgamap.daemon.store import CheckpointStore
    s = CheckpointStore(sys.argv[1]); i = 0
    print("go", flush=True)
    while True:
        i += 1
        s.save({"i": i, "seg": np.full((2000 + 37 * (i % 50), 4), float(i))})
""")


def kill_rounds(tmp_path, rounds: int, seed: int) -> int:
    rng = random.Random(seed)
    last = 0
    for r in range(rounds):
        proc = subprocess.Popen([sys.executable, "-c", KILLER, str(tmp_path)],
                                stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout.readline().strip() == "go"
            time.sleep(rng.uniform(0.0, 0.15))
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
        got = CheckpointStore(tmp_path).load()
        if r > 0 or got is not None:
            assert got is not None, f"round {r}: no readable checkpoint"
            assert np.all(got["seg"] == got["i"])
            last = got["i"]
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
    return last


def test_sigkill_during_checkpointing_few(tmp_path):
    kill_rounds(tmp_path, 5, seed=1)


@pytest.mark.slow
def test_sigkill_during_checkpointing_soak(tmp_path):
    kill_rounds(tmp_path, 200, seed=int(os.environ.get("CGAMAP_SOAK_SEED", "7")))
