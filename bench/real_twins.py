"""The twin check: a checkpoint on real frames and on their rendered twins, side by side, per object.

The twins (`axispose_core/data/twins.py`) keep the real background, clutter, camera, poses and framing, and swap
the annotated objects' look for the project's renders. What a checkpoint gains on the twins over the frames is
what the objects' real appearance costs it; what it still misses on the twins comes from the scene (background,
clutter, occlusion, framing). A third pass, "matched", keeps the real objects but gives each instance's pixels its
render's colour statistics (per channel mean and standard deviation over the pixels the render shows of it): what
that recovers of the twins' gain is first- and second-order colour (exposure, white balance, contrast), what it
does not is the objects' finer look (texture, shading, highlights). Every pass runs `axispose validate`'s settings
(GT crops and the localiser). Per object, the real pixels' luma, saturation and luma contrast over the render's.
The twins can be drawn otherwise, to ask what a checkpoint reads from renders: under another light (`--light`,
e.g. strong highlights), in each object's mean colour (`--colours mean`: shape and shading alone) or in a wrong
surface (`--colours wrong`), or through a worse camera (`--sensor`: blur, noise, JPEG); or take only part of the
objects' look from the render (`--part`: the inside of the silhouettes or the band along them, the coarse look or
the fine detail; `twins.TwinPart`), to tell where on the object the real look costs; give such a run its own --out.

    python bench/real_twins.py [--checkpoint CKPT] [--data ../shared/data/lmo_real_val/test] [--out out/twins]
        [--light AMBIENT,SPECULAR,SHININESS] [--colours scan|mean|wrong] [--sensor SIGMA,NOISE,JPEG_QUALITY]
        [--part inside|edge|coarse|fine,PX]

Writes OUT/twins/ and OUT/matched/ (the splits, reused on later calls), OUT/{real,twins,matched}.json, OUT/look.json
and OUT/table.txt.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import torch

from axispose_core.data.bop import read_bgr
from axispose_core.data.bop_scene import BopScene, scene_dirs
from axispose_core.data.meshes import load_render_mesh
from axispose_core.data.synth.randomize import jpeg
from axispose_core.data.synth.raster import Light, render
from axispose_core.data.twins import PARTS, TWIN_LIGHT, TwinPart, copy_annotations, write_twins
from axispose_core.estimator import SHIPPED_ESTIMATOR
from axispose_core.lmo import REAL_SLICE, SHARED_LMO
from axispose_core.validation import COLUMNS, ValidationSettings, format_cell, report_value, validate

PASSES = ("real", "twins", "matched")


def table(reports: dict[str, dict], look: dict[str, dict]) -> str:
    """`axispose validate`'s columns, means per pass, then per object the GT crops' Reproj@15px and rotation median
    and the localiser's recall per pass, and the real pixels' look over the render's."""
    lines = [f"{'':<12}" + "".join(f"{p:>9}" for p in PASSES)]
    for name, crops, key, fmt in COLUMNS:
        lines.append(f"{name:<12}" + "".join(f"{format_cell(report_value(reports[p], crops, key), fmt):>9}" for p in PASSES))
    lines.append("")
    head = "".join(f"{what + ' ' + p[:4]:>12}" for what in ("Rp15", "rot", "det R") for p in PASSES)
    lines.append(f"{'object':<12}{head} {'luma':>6} {'sat':>6} {'contr':>6}")
    for obj, entry in reports["real"]["gt"]["objects"].items():
        cells = [format_cell(report_value(reports[p], crops, key, obj), fmt)
                 for crops, key, fmt in (("gt", "reproj_15px", ".3f"), ("gt", "rot_err_median_deg", ".1f"), ("detect", "det_recall", ".2f"))
                 for p in PASSES]  # fmt: skip
        ratios = look.get(obj, {})
        lines.append(f"{entry['name']:<12}" + "".join(f"{c:>12}" for c in cells)
                     + "".join(f" {ratios.get(k, float('nan')):>6.2f}" for k in ("luma", "saturation", "contrast")))  # fmt: skip
    return "\n".join(lines)


def _stats(pixels: np.ndarray) -> tuple[float, float, float]:
    """Luma mean, saturation mean and luma standard deviation of (N,3) RGB in [0,1]."""
    luma = pixels @ np.array([0.299, 0.587, 0.114])
    sat = (pixels.max(axis=1) - pixels.min(axis=1)) / np.maximum(pixels.max(axis=1), 1e-6)
    return float(luma.mean()), float(sat.mean()), float(luma.std())


def write_matched(data: str | Path, models: str | Path, out: Path) -> dict[str, dict]:
    """The split `data` with each annotated instance's visible pixels given its render's per-channel mean and
    standard deviation (under the twins' light), written under `out`; returns per object id the medians over
    instances of the real pixels' luma, saturation and contrast over the render's."""
    meshes, ratios = {}, {}
    for scene_dir in scene_dirs(data):
        scene, target = BopScene(scene_dir), out / scene_dir.name
        (target / "rgb").mkdir(parents=True, exist_ok=True)
        for im_id in scene.image_ids:
            gts = scene.gt[im_id]
            for g in gts:
                meshes.setdefault(g.obj_id, load_render_mesh(models, g.obj_id))
            rgb = read_bgr(scene.rgb_path(im_id))[..., ::-1].astype(np.float64) / 255.0
            res = render([(meshes[g.obj_id], g.R, g.t) for g in gts], scene.cameras[im_id], rgb.shape[1], rgb.shape[0], TWIN_LIGHT)
            matched, drawn = rgb.copy(), np.asarray(res.rgb, np.float64)
            for k, g in enumerate(gts):
                mask = res.instance == k
                if mask.sum() < 20:
                    continue
                real, rendered = rgb[mask], drawn[mask]
                (lr, sr, cr), (lt, st, ct) = _stats(real), _stats(rendered)
                ratios.setdefault(g.obj_id, []).append((lr / max(lt, 1e-6), sr / max(st, 1e-6), cr / max(ct, 1e-6)))
                z = (real - real.mean(axis=0)) / np.maximum(real.std(axis=0), 1e-3)
                matched[mask] = np.clip(z * rendered.std(axis=0) + rendered.mean(axis=0), 0.0, 1.0)
            cv2.imwrite(str(target / "rgb" / f"{im_id:06d}.png"), np.round(matched[..., ::-1] * 255.0).astype(np.uint8))
        copy_annotations(scene_dir, target)
    names = ("luma", "saturation", "contrast")
    return {str(o): dict(zip(names, np.median(np.array(r), axis=0).tolist(), strict=True)) for o, r in ratios.items()}


def degrade(split: Path, sigma: float, noise: float, quality: int) -> None:
    """Every frame of `split` blurred (Gaussian, `sigma` px), noised (`noise`, of the range) and JPEG-compressed,
    in place, once (`sensor.json` records it)."""
    if (split / "sensor.json").exists():
        return
    rng = np.random.default_rng(0)
    for png in sorted(split.glob("*/rgb/*.png")):
        bgr = cv2.imread(str(png)).astype(np.float32) / 255.0
        bgr = cv2.GaussianBlur(bgr, (0, 0), sigma) if sigma > 0 else bgr
        bgr = np.clip(bgr + rng.normal(0.0, noise, bgr.shape), 0.0, 1.0)
        cv2.imwrite(str(png), np.round(jpeg(bgr[..., ::-1], quality)[..., ::-1] * 255.0).astype(np.uint8))
    (split / "sensor.json").write_text(json.dumps({"sigma": sigma, "noise": noise, "jpeg_quality": quality}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=str(SHIPPED_ESTIMATOR))
    ap.add_argument("--data", default=str(REAL_SLICE), help="a BOP split of real frames (default: the real validation slice)")
    ap.add_argument("--models", default=str(SHARED_LMO / "models"), help="full-resolution models: the twins' renders")
    ap.add_argument("--eval-models", default=str(SHARED_LMO / "models_eval"), help="models the metrics and visibility use")
    ap.add_argument("--out", default="out/twins")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--light", help="the twins' light: AMBIENT,SPECULAR,SHININESS (default: the twin light's)")
    ap.add_argument("--colours", choices=["scan", "mean", "wrong"], default="scan", help="the twins' surfaces (twins.write_twins)")
    ap.add_argument("--sensor", help="twins through a worse camera: BLUR_SIGMA,NOISE,JPEG_QUALITY")
    ap.add_argument("--part", help=f"the twins take only this of the objects from the render: PART,PX, PART one of {', '.join(PARTS[1:])}")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    light = TWIN_LIGHT
    if args.light:
        ambient, specular, shininess = (float(v) for v in args.light.split(","))
        light = Light(TWIN_LIGHT.direction, TWIN_LIGHT.color, ambient, specular, shininess)
    part = TwinPart()
    if args.part:
        name, px = args.part.split(",")
        part = TwinPart(name, float(px))
    splits = {"real": Path(args.data), "twins": write_twins(args.data, args.models, out / "twins", light, args.colours, part)}
    if args.sensor:
        sigma, noise, quality = args.sensor.split(",")
        degrade(splits["twins"], float(sigma), float(noise), int(quality))
    if not (out / "look.json").exists():
        shutil.rmtree(out / "matched", ignore_errors=True)
        (out / "look.json").write_text(json.dumps(write_matched(args.data, args.models, out / "matched"), indent=1))
    splits["matched"] = out / "matched"
    look = json.loads((out / "look.json").read_text())
    settings = ValidationSettings()
    reports = {}
    for name, data in splits.items():
        reports[name] = validate(args.checkpoint, data, args.eval_models, settings)
        (out / f"{name}.json").write_text(json.dumps(reports[name], indent=1))
    text = table(reports, look)
    (out / "table.txt").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
