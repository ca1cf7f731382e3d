"""Peak memory of ``rt-ident identify`` against the recording's length.

    python tools/identify_memory.py                 # 1 and 10 minutes at the sim's 34 k samples/s
    python tools/identify_memory.py --minutes 1 10 60

For each length a recording is written the way ``rt-ident run`` writes one (the sim plant, the
Schroeder multisine, the run's metadata, :class:`rt_ident.processes.recorder.Recorder`), then
``rt-ident identify FILE`` runs in a child process and its peak resident memory (``ru_maxrss``) is
read; as the peer in the same run, the same file is read whole (``read_recording``) in another
child. Prints minutes, samples, file size, peak RSS of identify (streamed) and of the whole read,
and the identified parameters' worst error against the plant.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DT = 2.9481e-5


def write_recording(path: Path, minutes: float) -> int:
    from rt_ident.axis.excitation import schroeder_multisine
    from rt_ident.axis.params import thomson_x
    from rt_ident.axis.plant import HoldController, PlantSimulator, SensorConfig
    from rt_ident.processes.recorder import Recorder

    p = thomson_x()
    ms = schroeder_multisine(512, (1, 20), peak=0.3)
    sim = PlantSimulator(p, DT, sensors=SensorConfig(torque_meas_noise=5e-4), controller=HoldController(), seed=1)
    meta = {"backend": "sim", "sample_period": DT, "axis": p.as_dict(), "method": "frequency", "warmup_periods": 2,
            "forgetting": 1.0, "excitation": {"kind": "schroeder", "period_samples": 512, "band": [1, 20],
                                              "peak": 0.3}}
    n_total = int(minutes * 60 / DT)
    chunk = 1 << 18
    with Recorder(path, meta, flush_interval=1.0) as rec:
        k = 0
        while k < n_total:
            n = min(chunk, n_total - k)
            u = ms.at(np.arange(k, k + n))
            b = sim.step_block(u)
            rec.append(np.arange(k, k + n) * DT, np.arange(k, k + n), b.theta1, b.theta2, b.torque_cmd,
                       b.torque_meas)
            rec.flush()
            k += n
    return n_total


def _peak_rss_mb(code: list[str]) -> tuple[float, str]:
    """Run ``code``; its own peak RSS (wait4's rusage of that one child) in MB, and its stdout."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        p = subprocess.Popen(code, stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        if p.returncode != 0:
            raise RuntimeError(err.read()[-2000:])
        return usage.ru_maxrss / 1024.0, out.read()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[1.0, 10.0])
    ap.add_argument("--peer-max-minutes", type=float, default=10.0,
                    help="read longer recordings whole only up to this length (memory)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="rt-ident-mem-") as t:
        for minutes in sorted(args.minutes):
            path = Path(t) / f"rec-{minutes:g}min.parquet"
            t0 = time.monotonic()
            n = write_recording(path, minutes)
            written = time.monotonic() - t0
            streamed, out = _peak_rss_mb([sys.executable, "-m", "rt_ident", "identify", str(path), "--json"])
            whole = float("nan")
            if minutes <= args.peer_max_minutes:     # the whole read needs ~120 B/sample: 15 GB for an hour
                whole, _ = _peak_rss_mb([sys.executable, "-c", "import sys; from rt_ident.processes.recorder "
                                         "import read_recording; r = read_recording(sys.argv[1]); print(len(r))",
                                         str(path)])
            d = json.loads(out)
            p = d.get("parameters") or {}
            truth = {"I1": 2.7e-5, "I2": 8.3e-6, "B": 2.1e-3, "K": 110.0}
            err = max(abs(p[k] / v - 1) for k, v in truth.items()) if p else float("nan")
            rows.append((minutes, n, path.stat().st_size / 2**20, streamed, whole, err, written))
            print(f"{minutes:>6g} min  {n:>11,d} samples  file {rows[-1][2]:8.1f} MiB  identify peak RSS "
                  f"{streamed:7.0f} MB  (whole read: {whole:7.0f} MB)  worst error {100 * err:.2f} %  "
                  f"[written in {written:.0f} s]", flush=True)
    if len(rows) >= 2:
        a, b = rows[0], rows[-1]
        print(f"identify peak RSS x{b[3] / a[3]:.2f} for x{b[1] / a[1]:.0f} the samples "
              f"(whole read: x{b[4] / a[4]:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
