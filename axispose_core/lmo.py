"""LINEMOD-Occluded (LM-O), the dataset the shipped model knows: its camera and objects, embedded so that demos,
tests and the crop stream run without the dataset on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np

SHARED_LMO = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo"
"""LM-O in BOP layout (models, models_eval, camera) beside the clone, as CI lays it out."""
REAL_SLICE = SHARED_LMO.parent / "lmo_real_val" / "test"
"""The real validation slice: 40 real LM-O frames (scene 2), for choosing between designs only."""

LMO_K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
"""The LM-O camera (640x480), embedded so that demos run without the dataset."""
LMO_SIZE = (640, 480)
LMO_DISTANCE = (0.35, 1.5)
"""Range of object distances (m) in the LM-O test images."""
LMO_NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher"}
"""Names of the eight LINEMOD-Occluded objects by BOP id."""
LMO_DIAMETERS = {1: 0.102099, 5: 0.201404, 6: 0.154546, 8: 0.261472, 9: 0.108999, 10: 0.164628, 11: 0.175889, 12: 0.145543}
"""Their model diameters in metres (models_info.json), so demos run without the dataset on disk."""
LMO_SYMMETRIC = frozenset({10, 11})
"""The symmetric ones (eggbox, glue), as models_info.json declares."""
