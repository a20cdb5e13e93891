"""The objects a model knows: id, name, size, axis lengths and symmetry; built from a BOP models folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from axispose_core.axis_image import AxisSpec
from axispose_core.data.bop import load_models_info

LMO_NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher"}
"""Names of the eight LINEMOD-Occluded objects by BOP id."""
LMO_DIAMETERS = {1: 0.102099, 5: 0.201404, 6: 0.154546, 8: 0.261472, 9: 0.108999, 10: 0.164628, 11: 0.175889, 12: 0.145543}
"""Their model diameters in metres (models_info.json), so demos run without the dataset on disk."""
LMO_SYMMETRIC = frozenset({10, 11})


@dataclass(frozen=True)
class ObjectSpec:
    """What the TBM and the metrics need of one object; serialisable into checkpoint configs."""

    obj_id: int
    name: str
    diameter: float
    scale: float
    ratio_b: float = 1.0
    ratio_c: float = 1.0
    symmetric: bool = False

    @property
    def axes(self) -> AxisSpec:
        return AxisSpec(self.scale, self.ratio_b, self.ratio_c)


def lmo_objects() -> list[ObjectSpec]:
    """The embedded LM-O object list with the default λ_O = half the diameter."""
    return [ObjectSpec(i, LMO_NAMES[i], d, 0.5 * d, symmetric=i in LMO_SYMMETRIC) for i, d in sorted(LMO_DIAMETERS.items())]


def objects_from_models(models_dir: str | Path, obj_ids: list[int] | None = None, names: dict[int, str] | None = None) -> list[ObjectSpec]:
    """ObjectSpecs from a BOP folder's models_info.json (λ_O = half the diameter; unnamed ids become obj_<id>)."""
    infos = load_models_info(Path(models_dir) / "models_info.json")
    names = names or {}
    ids = sorted(infos) if obj_ids is None else obj_ids
    missing = [i for i in ids if i not in infos]
    if missing:
        raise ValueError(f"{models_dir}/models_info.json has no object(s) {missing}")
    return [
        ObjectSpec(i, names.get(i, f"obj_{i:06d}"), infos[i].diameter, 0.5 * infos[i].diameter, symmetric=infos[i].symmetric) for i in ids
    ]
