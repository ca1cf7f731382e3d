"""Stall drill: pause the whole XY CANopen run (SIGSTOP/SIGCONT) again and again while its drives keep
their last torque, and print how each stall ended.

    python tools/stall_drill.py                        # 6 s run, a 54 ms pause every 0.6 s
    python tools/stall_drill.py --pause 0.03 --every 0.3 --deadline-ms 200

The run is ``configs/xy-canopen-virtual.toml`` with the drives' RPDO deadline at ``--deadline-ms``
(shipped: 20 ms, which faults a drive on a longer pause; past it the drive applies its last torque
through the pause, as a real CiA 402 drive does), the watchdogs and speed limit widened so only the
travel guard and the rejoin are under test. The child prints its summary as JSON; this prints the stop,
each stall's re-plan (position, speed, braking) and each axis's error. Exit code 0 when the run ended
on its own.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time

CHILD = r"""
import json, sys
from rt_ident.compose.run import run
from rt_ident.config import load
over = {"loop.realtime": True, "telemetry.sink": "off", "recording.enabled": False,
        "backend.stale_limit": 1000, "backend.heartbeat_consumer_ms": 1000, "safety.watchdog_ticks": 500,
        "safety.max_speed_m_s": 1.0, "loop.duration": float(sys.argv[1]), "backend.rpdo_deadline_ms": int(sys.argv[2])}
if __name__ == "__main__":
    s = run(load(sys.argv[3], **over))
    print(json.dumps({"stop": {k: s["stop"].get(k) for k in ("cause", "message", "axis")},
                      "axes": {n: {"stalls": [e["detail"] for e in ax["control"].get("events", [])
                                              if e["kind"] == "stall"],
                                   "max_error_m": ax["control"]["max_error_m"]}
                               for n, ax in s["axes"].items()}}, default=str))
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="run length [s]")
    ap.add_argument("--pause", type=float, default=0.054, help="each pause [s]")
    ap.add_argument("--every", type=float, default=0.6, help="time between pauses [s]")
    ap.add_argument("--deadline-ms", type=int, default=200, help="the drives' RPDO deadline [ms]")
    ap.add_argument("--config", default=os.path.join(os.path.dirname(__file__), "..", "configs",
                                                      "xy-canopen-virtual.toml"))
    a = ap.parse_args(argv)
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(a.seconds), str(a.deadline_ms), a.config],
                             stdout=subprocess.PIPE, text=True)
    time.sleep(3.0)                                    # start-up: the drives enabled, the loop ticking
    pauses = 0
    try:
        while child.poll() is None:
            child.send_signal(signal.SIGSTOP)
            time.sleep(a.pause)
            child.send_signal(signal.SIGCONT)
            pauses += 1
            time.sleep(a.every)
    except ProcessLookupError:
        pass
    finally:
        if child.poll() is None:
            child.send_signal(signal.SIGCONT)
    out, _ = child.communicate()
    if child.returncode != 0 or not out.strip():
        print(f"the run exited {child.returncode} without a summary", file=sys.stderr)
        return 1
    s = json.loads(out.strip().splitlines()[-1])
    print(f"{pauses} pauses of {a.pause * 1e3:.0f} ms; deadline {a.deadline_ms} ms; stop: {s['stop']}")
    for name, ax in s["axes"].items():
        for d in ax["stalls"]:
            print(f"  {name}: {d}")
        err = ax["max_error_m"]
        print(f"  {name}: max error " + ("none (no control)" if err is None else f"{err * 1e3:.3f} mm"))
    return 0 if s["stop"]["cause"] is None else 1


if __name__ == "__main__":
    sys.exit(main())
