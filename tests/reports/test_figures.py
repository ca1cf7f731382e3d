"""The figure writers draw on their own ``Figure``: the caller's matplotlib backend and pyplot state are theirs."""

import subprocess
import sys

SCRIPT = r"""
import sys
import matplotlib
import numpy as np
matplotlib.use("pdf")                       # what a caller had chosen before calling us
import rt_ident.reports.figures             # noqa: F401 - its import alone once switched the backend
from rt_ident.bench.control import control_comparison
from rt_ident.control.contour import circle_figures, polar_plot

out = sys.argv[1]
th = np.linspace(0.0, 2 * np.pi, 400)
paths = {"ccw": (1e-2 * np.cos(th), 1e-2 * np.sin(th) - 1e-2)}
polar_plot(paths, 1e-2, (0.0, -1e-2), circle_figures(paths, 1e-2, (0.0, -1e-2)), out + "/c.png")
err = {"rms_error_m": 2e-6, "max_error_m": 5e-6}
control_comparison({"control": {"scenarios": [{"name": "I2 x 3", "fixed": err, "adaptive": err, "oracle": err}]}},
                   out + "/b.png")
print(matplotlib.get_backend(), "matplotlib.pyplot" in sys.modules)
"""


def test_figures_leave_the_callers_backend_and_never_import_pyplot(tmp_path):
    p = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split() == ["pdf", "False"]
    for name in ("c.png", "b.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
