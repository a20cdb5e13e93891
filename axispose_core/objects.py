"""What the estimator knows of an object at run time: id, name, size, axis lengths and symmetry (read from data by
`data/objects.py`), and the embedded LM-O list."""

from __future__ import annotations

from dataclasses import dataclass

from axispose_core.axis_image import AxisSpec
from axispose_core.lmo import LMO_DIAMETERS, LMO_NAMES, LMO_SYMMETRIC


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
