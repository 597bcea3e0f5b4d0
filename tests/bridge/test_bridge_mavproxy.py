"""MAVProxy (PyPI `mavproxy`) connects non-interactively to the loopback vehicle and sees its
HEARTBEAT and ODOMETRY (checked in the tlog MAVProxy writes)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections import Counter

import pytest

os.environ.setdefault("MAVLINK20", "1")

from _bridge import VehicleProcess, free_base_port  # noqa: E402


def _mavproxy():
    exe = os.path.join(os.path.dirname(sys.executable), "mavproxy.py")
    if os.path.exists(exe):
        return [sys.executable, exe]
    found = shutil.which("mavproxy.py")
    return [sys.executable, found] if found else None


@pytest.mark.realtime
@pytest.mark.timeout(90)
def test_mavproxy_sees_heartbeat_and_odometry(tmp_path):
    mp = _mavproxy()
    if mp is None:
        pytest.skip("MAVProxy is not installed (pip install mavproxy; it is in the test extra)")
    port = free_base_port(1)
    tlog = tmp_path / "mavproxy.tlog"
    with VehicleProcess(["--count", "1", "--base-port", port, "--duration", "30"], tmp_path):
        proc = subprocess.Popen(mp + [f"--master=udpin:127.0.0.1:{port}", "--non-interactive", "--daemon",
                                      f"--logfile={tlog}", f"--state-basedir={tmp_path}", "--default-modules="],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                cwd=str(tmp_path), env=dict(os.environ, MAVLINK20="1"))
        try:
            t_end = time.monotonic() + 40
            counts = Counter()
            while time.monotonic() < t_end and proc.poll() is None:
                time.sleep(1.0)
                counts = _count(tlog)
                if counts["HEARTBEAT"] >= 2 and counts["ODOMETRY"] >= 50:
                    break
        finally:
            proc.terminate()
            try:
                out = proc.communicate(timeout=10)[0]
            except subprocess.TimeoutExpired:
                proc.kill()
                out = proc.communicate()[0]
    counts = _count(tlog)
    text = out.decode(errors="replace")
    assert counts["HEARTBEAT"] >= 2 and counts["ODOMETRY"] >= 50, (counts, text[-2000:])
    assert "Detected vehicle 1:1" in text or "online system 1" in text, text[-2000:]


def _count(tlog) -> Counter:
    from pymavlink import mavutil

    c = Counter()
    if not os.path.exists(tlog) or os.path.getsize(tlog) == 0:
        return c
    m = mavutil.mavlink_connection(str(tlog))
    while True:
        try:
            x = m.recv_match()
        except Exception:  # noqa: BLE001 - a record being written right now
            break
        if x is None:
            break
        c[x.get_type()] += 1
    m.close()
    return c
