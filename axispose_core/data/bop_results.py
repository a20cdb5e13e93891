"""BOP19 results files: one estimated pose a line, as the official toolkit reads and writes them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from axispose_core.data.bop import MM, BopFormatError


@dataclass(frozen=True)
class BopEstimate:
    """One line of a BOP19 results file: a pose (metres here, mm in the file) with its score and the time its
    image took (s; -1 unknown)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0


RESULTS_HEADER = "scene_id,im_id,obj_id,score,R,t,time"


def write_bop_results(path: str | Path, estimates: list[BopEstimate]) -> None:
    """A BOP19 results CSV, as the official toolkit reads it (name it METHOD_DATASET-SPLIT.csv for its scripts)."""
    lines = [RESULTS_HEADER]
    for e in estimates:
        R = " ".join(repr(float(v)) for v in np.asarray(e.R, np.float64).ravel())
        t = " ".join(repr(float(v)) for v in np.asarray(e.t, np.float64).ravel() / MM)
        lines.append(f"{e.scene_id},{e.im_id},{e.obj_id},{float(e.score)!r},{R},{t},{float(e.time)!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def read_bop_results(path: str | Path) -> list[BopEstimate]:
    """A BOP19 results CSV (header optional, as the official toolkit allows)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise BopFormatError(f"{path}: cannot read ({err})") from err
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or (n == 1 and RESULTS_HEADER in line):
            continue
        cells = line.split(",")
        if len(cells) != 7:
            raise BopFormatError(f"{path}: line {n}: expected 7 comma-separated fields, got {len(cells)}")
        try:
            ids = [int(c) for c in cells[:3]]
            R = np.array(cells[4].split(), np.float64).reshape(3, 3)
            t = np.array(cells[5].split(), np.float64).reshape(3) * MM
            out.append(BopEstimate(*ids, float(cells[3]), R, t, float(cells[6])))
        except ValueError as err:
            raise BopFormatError(f"{path}: line {n}: {err}") from err
    return out
