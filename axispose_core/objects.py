"""The objects a model knows (`ObjectSpec`: id, name, size, axis lengths, symmetry) and every way to get them: the
embedded LM-O list, a BOP models folder (models_info.json and names.json), or the folders of a dataset.

One home, so the estimator, the trainers and the data tools agree on what an object is; LM-O's own numbers stay
in lmo.py, with its camera.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from axispose_core.axis_image import AxisSpec
from axispose_core.lmo import LMO_DIAMETERS, LMO_NAMES, LMO_SYMMETRIC

if TYPE_CHECKING:  # the node reads objects from its checkpoint; the BOP readers load only where a models folder is read
    from axispose_core.data.bop_models import ObjectInfo

NAMES_FILE = "names.json"
"""Beside models_info.json: {"<obj_id>": "<name>"}, written by `axispose synth` from the imported meshes' file names."""
NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
"""An object name: it becomes part of the node's topic and parameter names, so ROS's rules for a name token."""


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


def object_name(stem: str, obj_id: int) -> str:
    """A valid object name from a file name: other characters become '_', lower case, obj_<id> if nothing is left."""
    name = re.sub(r"[^a-z0-9_]+", "_", stem.lower()).strip("_")
    return name if NAME.fullmatch(name) else f"obj_{obj_id:06d}"


def is_lmo(infos: dict[int, ObjectInfo]) -> bool:
    """Whether a models_info.json describes LM-O objects: each id one of LM-O's with its diameter (to 0.1 mm)."""
    return bool(infos) and all(i in LMO_DIAMETERS and abs(info.diameter - LMO_DIAMETERS[i]) < 1e-4 for i, info in infos.items())


def object_names(models_dir: str | Path, infos: dict[int, ObjectInfo] | None = None) -> dict[int, str]:
    """The names of a models folder's objects: its names.json, else LM-O's names for LM-O's models (`infos`: its
    models_info.json where the caller has read it), else none."""
    path = Path(models_dir) / NAMES_FILE
    if path.exists():
        try:
            names = {int(k): str(v) for k, v in json.loads(path.read_text()).items()}
        except (ValueError, AttributeError) as err:
            raise ValueError(f'{path}: expected {{"<obj_id>": "<name>"}} ({err})') from err
        bad = sorted(n for n in names.values() if not NAME.fullmatch(n))
        if bad or len(set(names.values())) < len(names):
            raise ValueError(f"{path}: names must be distinct, start with a letter and hold only letters, digits and '_' "
                             f"(topic and parameter names are made of them): {bad or sorted(names.values())}")  # fmt: skip
        return names
    from axispose_core.data.bop_models import load_models_info

    infos = load_models_info(Path(models_dir) / "models_info.json") if infos is None else infos
    return dict(LMO_NAMES) if is_lmo(infos) else {}


def objects_from_models(models_dir: str | Path, obj_ids: list[int] | None = None, names: dict[int, str] | None = None) -> list[ObjectSpec]:
    """ObjectSpecs from a BOP folder's models_info.json (λ_O = half the diameter), named by `names`, else by
    `object_names`; unnamed ids become obj_<id>."""
    from axispose_core.data.bop_models import load_models_info

    infos = load_models_info(Path(models_dir) / "models_info.json")
    names = object_names(models_dir, infos) if names is None else names
    ids = sorted(infos) if obj_ids is None else obj_ids
    missing = [i for i in ids if i not in infos]
    if missing:
        raise ValueError(f"{models_dir}/models_info.json has no object(s) {missing}")
    return [
        ObjectSpec(i, names.get(i, f"obj_{i:06d}"), infos[i].diameter, 0.5 * infos[i].diameter, symmetric=infos[i].symmetric) for i in ids
    ]


def dataset_objects(roots: list[str | Path]) -> list[ObjectSpec]:
    """The objects BOP data folders show, by id: each folder's synthetic objects (its synth_config.json), else all
    of its models_info.json; folders that share an id must agree on its size."""
    from axispose_core.data.synth.config import SynthConfig  # the synthetic data's record, not a models folder

    found: dict[int, tuple[ObjectSpec, Path]] = {}
    for root in map(Path, roots):
        synth = root / "synth_config.json"
        ids = list(SynthConfig.load(synth).objects) if synth.exists() else None
        for spec in objects_from_models(root, ids or None):
            seen = found.setdefault(spec.obj_id, (spec, root))
            if abs(seen[0].diameter - spec.diameter) > 1e-6:
                raise ValueError(
                    f"object {spec.obj_id} has diameter {seen[0].diameter:.4f} m in {seen[1]} but {spec.diameter:.4f} m in {root}"
                )
    return [spec for _, (spec, _) in sorted(found.items())]
