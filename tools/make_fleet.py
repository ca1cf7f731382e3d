#!/usr/bin/env python
"""``rt-ident fleet make`` for scripts that call ``python tools/make_fleet.py OUT ...`` (same options; see
:mod:`rt_ident.fleet.make`). It runs the ``rt_ident`` of the checkout it sits in.

    python tools/make_fleet.py OUT --machines 4 --axes x,y --days 12 --worn 0.5 --seed 1
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from rt_ident.fleet.make import main  # noqa: E402 - after the checkout is on the path

if __name__ == "__main__":
    raise SystemExit(main())
