"""Values printed in the paper's Tables 2-6, for side-by-side reporting.

Transcribed from the paper (decimal commas turned into points). Keys follow
the JSON of ``rt-ident reproduce --json``. Each case is keyed by (N, k).
"""

from __future__ import annotations

TABLE1 = {"I1": 2.7e-5, "I2": 8.3e-6, "B": 2.1e-3, "K": 1.1e2}

# Table 2: (N, k, wn, w0, dt)
TABLE2 = (
    {"N": 512, "k": 10, "wn": 4.1626e3, "w0": 416.2582, "dt": 2.9481e-5},
    {"N": 2048, "k": 146, "wn": 4.1626e3, "w0": 28.5108, "dt": 1.0761e-4},
)

# Tables 3 and 5 (physical) and 4 and 6 (modal): estimated value and error % per case.
# The paper repeats wn/wd/zeta for "mode 1" and "mode 2" with equal values; one is kept.
LS = {
    (512, 10): {
        "estimate": {"I1": 2.7133e-5, "I2": 8.2999e-6, "B": 1.4e-3, "K": 1.0905e2,
                     "wn": 4.1423e3, "wd": 4.1410e3, "zeta": 2.59e-2},
        "error_pct": {"I1": 4.9e-1, "I2": 7.05e-6, "B": 3.509e1, "K": 8.5e-1,
                      "wn": 4.8e-1, "wd": 4.4e-1, "zeta": 3.48e1},
    },
    (2048, 146): {
        "estimate": {"I1": 2.702e-5, "I2": 8.29999e-6, "B": 7.4e-3, "K": 1.03e2,
                     "wn": 4.0276e3, "wd": 3.9852e3, "zeta": 1.447e-1},
        "error_pct": {"I1": 7.6e-2, "I2": 1.06e-7, "B": 2.52e2, "K": 6.36,
                      "wn": 3.24, "wd": 4.18, "zeta": 2.64e2},
    },
}
RLS = {
    (512, 10): {
        "estimate": {"I1": 2.699e-5, "I2": 8.299e-6, "B": 2.08e-3, "K": 1.0994e2,
                     "wn": 4.1617e3, "wd": 4.1585e3, "zeta": 3.95e-2},
        "error_pct": {"I1": 3.67e-2, "I2": 2.75e-4, "B": 6.64e-1, "K": 4.89e-2,
                      "wn": 2e-2, "wd": 1.9e-2, "zeta": 6.36e-1},
    },
    (2048, 146): {
        "estimate": {"I1": 2.69998e-5, "I2": 8.29999e-6, "B": 2.0998e-3, "K": 1.0999e2,
                     "wn": 4.16257e3, "wd": 4.15928e3, "zeta": 3.973e-2},
        "error_pct": {"I1": 6.81e-4, "I2": 3.6e-7, "B": 5.0e-3, "K": 5.8e-4,
                      "wn": 2.11e-4, "wd": 2.04e-4, "zeta": 4.6e-3},
    },
}
