"""BOP object models: the model file of an object id and models_info.json (diameters, boxes, symmetries), in
metres."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from axispose_core.data.bop import MM, BopFormatError, keyed, numbers, required, write_json


def model_path(models_dir: str | Path, obj_id: int) -> Path:
    """BOP model file name of an object id."""
    return Path(models_dir) / f"obj_{obj_id:06d}.ply"


@dataclass(frozen=True)
class ObjectInfo:
    """One entry of models_info.json, in metres."""

    obj_id: int
    diameter: float
    bbox_min: np.ndarray
    bbox_size: np.ndarray
    symmetries_discrete: tuple[np.ndarray, ...] = ()
    symmetries_continuous: tuple[dict[str, Any], ...] = ()
    """{"axis": 3 numbers, "offset": 3 numbers in metres} each: rotation about the axis through the offset."""

    @property
    def symmetric(self) -> bool:
        """Whether ADD-S (not ADD) scores this object."""
        return bool(self.symmetries_discrete or self.symmetries_continuous)


def load_models_info(path: str | Path) -> dict[int, ObjectInfo]:
    """models_info.json as ObjectInfo by object id (diameters, boxes and symmetry offsets converted to metres)."""
    path = Path(path)
    infos = {}
    for obj_id, entry in keyed(path, "object"):
        where = f"object {obj_id}"
        diameter = float(numbers(path, where, "diameter", required(path, where, entry, "diameter"), 1)[0]) * MM
        if diameter <= 0:
            raise BopFormatError(f"{path}: {where}: field 'diameter' must be positive")
        bbox_min = np.array([numbers(path, where, f"min_{a}", required(path, where, entry, f"min_{a}"), 1)[0] for a in "xyz"]) * MM
        bbox_size = np.array([numbers(path, where, f"size_{a}", required(path, where, entry, f"size_{a}"), 1)[0] for a in "xyz"]) * MM
        syms = []
        for k, s in enumerate(entry.get("symmetries_discrete", [])):
            T = numbers(path, where, f"symmetries_discrete[{k}]", s, 16).reshape(4, 4)
            T[:3, 3] *= MM
            syms.append(T)
        cont = []
        for k, s in enumerate(entry.get("symmetries_continuous", [])):
            where_k = f"{where} symmetries_continuous[{k}]"
            axis = numbers(path, where_k, "axis", required(path, where_k, s, "axis"), 3)
            if not np.linalg.norm(axis) > 0:
                raise BopFormatError(f"{path}: {where_k}: field 'axis' must not be zero")
            offset = numbers(path, where_k, "offset", s.get("offset", [0.0, 0.0, 0.0]), 3) * MM
            cont.append({"axis": axis.tolist(), "offset": offset.tolist()})
        infos[obj_id] = ObjectInfo(obj_id, diameter, bbox_min, bbox_size, tuple(syms), tuple(cont))
    return infos


def write_models_info(path: str | Path, infos: dict[int, ObjectInfo]) -> None:
    """Write models_info.json (mm) from ObjectInfo in metres."""
    out = {}
    for obj_id, info in sorted(infos.items()):
        entry: dict[str, Any] = {"diameter": info.diameter / MM}
        for i, a in enumerate("xyz"):
            entry[f"min_{a}"] = info.bbox_min[i] / MM
            entry[f"size_{a}"] = info.bbox_size[i] / MM
        if info.symmetries_discrete:
            syms = []
            for T in info.symmetries_discrete:
                T = np.array(T, dtype=np.float64)
                T[:3, 3] /= MM
                syms.append(T.ravel().tolist())
            entry["symmetries_discrete"] = syms
        if info.symmetries_continuous:
            entry["symmetries_continuous"] = [
                {"axis": list(s["axis"]), "offset": (np.asarray(s["offset"], np.float64) / MM).tolist()} for s in info.symmetries_continuous
            ]
        out[str(obj_id)] = entry
    write_json(Path(path), out)
