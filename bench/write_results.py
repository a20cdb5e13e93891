"""What every benchmark script ends with: its results as JSON, stamped with the machine and date it ran on.

The scripts run as `python bench/NAME.py`, so this folder is on sys.path and they `from write_results import ...`.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path


def write_results(path: str | Path, results: dict | list) -> None:
    """Write `results` to `path` (folders made); a dict gets "machine" and "date" unless it names its own."""
    if isinstance(results, dict):
        results = {"machine": platform.processor() or platform.machine(), "date": time.strftime("%Y-%m-%d")} | results
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(results, indent=1))
    print(f"wrote {path}")
