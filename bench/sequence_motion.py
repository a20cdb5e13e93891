"""How far a scene's consecutive frames lie apart (`tracking/motion.py`): the camera's rotation between frames, how
far the objects' centres move in the image, and how often an object moves against the rest (its centre more than
`--tol` off the camera's motion: the object moved, or its annotation did), in all and per object.

    python bench/sequence_motion.py ../shared/data/lmo_real_val/test/000002 [SCENE ...] [--tol 0.02]
"""

from __future__ import annotations

import argparse

from axispose_core.data.bop_scene import BopScene
from axispose_core.tracking.motion import scene_motion


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", help="BOP scene folders (scene_gt.json, scene_camera.json)")
    ap.add_argument("--tol", type=float, default=0.02, help="an object off the camera's motion by more than this (m) moved")
    args = ap.parse_args()
    for root in args.scenes:
        try:
            m = scene_motion(BopScene(root), args.tol)
        except (OSError, ValueError) as exc:
            ap.exit(2, f"sequence_motion: {exc}\n")
        print(f"{root}: {m['frames']} frames; between consecutive frames the camera turns {m['rotation_deg_median']:.1f}° "
              f"(q75 {m['rotation_deg_q75']:.1f}°), objects move {m['image_motion_px_median']:.0f} px "
              f"(q75 {m['image_motion_px_q75']:.0f} px) in the image; {m['objects_moved_share']:.1%} of object steps "
              "move against the rest")  # fmt: skip
        print("  moves per object: " + ", ".join(f"{obj_id}: {n}" for obj_id, n in sorted(m["moves"].items())))


if __name__ == "__main__":
    main()
