"""The `axispose` command line: the core commands plus those on rosbag2 recordings (`make-bag`, `replay`).

ROS imports stay inside the handlers, so the core commands run where only `axispose_core` is installed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from axispose_core.cli import build_parser
from axispose_core.cli import main as core_main
from axispose_core.command_args import AddParser, object_ids
from axispose_core.lmo import SHARED_LMO
from axispose_core.tracking.mode import Mode

REPLAY_PARAMS = {
    "steps": "ddim_steps", "hypotheses": "hypotheses", "guidance": "guidance_scale", "precision": "precision", "mode": "mode",
    "refine": "refine", "redetect_period": "redetect_period", "measure_every": "measure_every", "view_window": "view_window",
    "follow_passes": "follow_passes",
}  # fmt: skip
MODES = [m.value for m in Mode]
"""`replay`'s options that set the node's parameter of that name ("on" / "off": True / False)."""


def _refused(command: str, err: Exception) -> int:
    """A command that cannot start: its reason on one line of stderr (whatever newlines it holds), exit code 2."""
    print(f"axispose {command}: {' '.join(str(err).split())}", file=sys.stderr)
    return 2


def _make_bag(args: argparse.Namespace) -> int:
    from axispose_core.objects import objects_from_models
    from axispose_ros.bag import BagOptions, make_bag

    try:
        objects = objects_from_models(args.models, args.objects or None)
        options = BagOptions(storage=args.format, fps=args.fps, limit=args.limit, stamp_by_id=args.stamp_by_id)
        s = make_bag(args.data, args.out, objects, args.models, options)
    except (FileExistsError, FileNotFoundError, ValueError) as err:  # an output that exists, data or models missing, a bad option
        return _refused("make-bag", err)
    print(f"wrote {s.path} ({args.format}): {s.frames} frames, {s.instances} GT instances, {s.bytes / 1e6:.1f} MB")
    return 0


def _replay(args: argparse.Namespace) -> int:
    from rclpy.exceptions import ParameterException

    from axispose_core.checkpoint import CheckpointError
    from axispose_core.evaluation.report import format_table, write_report
    from axispose_ros.bag import BagError
    from axispose_ros.replay import ReplayOptions, replay

    params: dict[str, object] = {"num_threads": args.threads}
    for arg, name in REPLAY_PARAMS.items():
        if (value := getattr(args, arg)) is not None:
            params[name] = value == "on" if value in ("on", "off") else value
    options = ReplayOptions(
        rate=None if args.as_fast_as_possible else args.rate, params=params, image_topic=args.image_topic,
        info_topic=args.camera_info_topic, odom_topic=args.odom_topic, storage=args.format, overlays=args.overlays,
        use_rois=not args.ignore_rois,
    )  # fmt: skip
    if Path(args.out).exists():
        print(f"axispose replay: {args.out} exists; rosbag2 writers refuse to overwrite a bag", file=sys.stderr)
        return 2
    try:
        result = replay(args.bag, args.checkpoint, args.out, options)
    except BagError as err:
        print(f"axispose replay: {err}", file=sys.stderr)
        if Path(args.out).exists():
            print(f"axispose replay: what was recorded until then is in {args.out}", file=sys.stderr)
        return 2
    except (CheckpointError, ValueError, ParameterException) as err:  # the node refused to start: checkpoint, parameters
        return _refused("replay", err)
    counts = ", ".join(f"{k} {v}" for k, v in sorted(result.counts.items()))
    print(f"replayed {result.frames_published} frames -> {result.out_bag}; node counters: {counts}")
    if result.report is not None:
        print(format_table(result.report))
        lat = result.report["frame_latency_ms"]
        own = result.report["node_frame_ms"]
        print(
            f"frame latency: median {lat['median']:.0f} ms, p90 {lat['p90']:.0f} ms (image published to ~/pose_array received); "
            f"the node's own, received to published, of its last {own['frames']} frames: "
            f"median {own['median']:.0f} ms, p90 {own['p90']:.0f} ms"
        )
        jit = result.report["tracking"]
        print(f"modes {jit['modes']}: jitter {jit['jitter_mm']:.1f} mm, {jit['jitter_deg']:.2f} deg "
              f"(median over {jit['n']} consecutive frame pairs)")  # fmt: skip
        if args.report:
            write_report(result.report, args.report)
            print(f"report: {args.report}")
    elif args.report:
        print("the bag has no /gt/<object> poses and /gt/models/<object> points: no metrics", file=sys.stderr)
    for path in result.overlays:
        print(f"overlay: {path}")
    print(
        "\nrun the node live on a camera:\n"
        f"  axispose_node --ros-args -p checkpoint:={Path(args.checkpoint).resolve()} "
        "-r image:=/camera/color/image_raw -r camera_info:=/camera/color/camera_info"
    )
    return 0


def build_ros_parser() -> argparse.ArgumentParser:
    """The core's commands plus the ROS ones."""
    return build_parser(_add_ros_commands)


def _soak(args: argparse.Namespace) -> int:
    from axispose_core.estimator import SHIPPED_ESTIMATOR
    from axispose_ros.bag import BagError
    from axispose_ros.soak import SoakOptions, soak

    opts = SoakOptions(seconds=args.minutes * 60, rate=args.rate, mode=args.mode, view_window=args.view_window,
                       follow_passes=args.follow_passes, faults=not args.no_faults,
                       precision=args.precision, threads=args.threads)  # fmt: skip
    try:
        r = soak(args.bag, args.checkpoint or SHIPPED_ESTIMATOR, opts, args.out)
    except (BagError, RuntimeError) as err:
        print(f"axispose soak: {err}", file=sys.stderr)
        return 2
    uncounted = [f["fault"] for f in r["faults"] if not f["counted"]]
    print(f"node {'alive' if r['alive'] else 'DIED'}; frames sent {r['frames_sent']}, arrived {r['frames_in']}, processed "
          f"{r['frames_processed']}, dropped {r['dropped']}; RSS {r['rss_mb']['after_first_minute']:.0f} -> "
          f"{r['rss_mb']['end']:.0f} MB ({100 * r['rss_growth']:+.1f} %); faults {len(r['faults'])}, not counted "
          f"{uncounted or 'none'}; tracking {r['tracking'] or '-'}; diagnostics {r['diagnostics_levels']}; "
          f"report {Path(args.out) / 'soak.json'}")  # fmt: skip
    return 0 if r["alive"] and not uncounted else 1


def _adapt(args: argparse.Namespace) -> int:
    import torch

    from axispose_core.adapt.command import AdaptRequest, run_adapt
    from axispose_core.adapt.recording import RecordingError
    from axispose_core.estimator import SHIPPED_ESTIMATOR

    torch.set_num_threads(args.threads)
    request = AdaptRequest(Path(args.recording), Path(args.out), Path(args.checkpoint or SHIPPED_ESTIMATOR), Path(args.models),
                           args.config, args.rounds, args.steps, args.resume, args.max_minutes, args.device)  # fmt: skip
    if not is_bag(args.recording):
        return run_adapt(request)
    from axispose_core.adapt.recording import read_recording
    from axispose_ros.recording import bag_to_recording

    frames = Path(args.out) / "recording"
    try:
        if not frames.is_dir():
            s = bag_to_recording(args.recording, frames, args.image_topic, args.camera_info_topic, args.odom_topic, args.every, args.limit)
            print(f"wrote {s.frames} frames of {args.recording} into {frames}" + (f"; skipped {s.skipped}" if s.skipped else ""))
        recording = read_recording(frames)
    except RecordingError as err:
        return _refused("adapt", err)
    return run_adapt(request, recording)


def is_bag(path: str | Path) -> bool:
    """Whether `path` is a rosbag2 (its folder with metadata.yaml, or an .mcap / .db3 file)."""
    path = Path(path)
    return (path / "metadata.yaml").is_file() or path.suffix in (".mcap", ".db3")


def _add_ros_commands(add_parser: AddParser) -> None:
    """`make-bag`, `replay`, `soak` and `adapt`: their handlers import ROS, the parser does not."""
    for add in (_add_make_bag, _add_replay, _add_soak, _add_adapt):
        add(add_parser)


def _add_make_bag(add_parser: AddParser) -> None:
    mb = add_parser("make-bag", help="write a BOP scene as a rosbag2: camera stream, GT poses, GT boxes, model points")
    mb.add_argument("--data", required=True, help="one BOP scene folder (rgb/, scene_gt.json, scene_camera.json)")
    mb.add_argument("--out", required=True, help="bag folder to create")
    mb.add_argument("--models", required=True, help="BOP models folder (names, metrics points; models_eval is enough)")
    mb.add_argument("--format", choices=["sqlite3", "mcap"], default="mcap")
    mb.add_argument("--objects", type=object_ids, default=[], help="comma-separated object ids (default: all in models_info.json)")
    mb.add_argument("--fps", type=float, default=10.0, help="frame rate the stamps are spaced by")
    mb.add_argument("--stamp-by-id", action="store_true", help="stamp each image at its image id / fps: a split that keeps every "
                    "n-th frame of a recording keeps the recording's timing")  # fmt: skip
    mb.add_argument("--limit", type=int, default=None, help="first N images only")
    mb.set_defaults(func=_make_bag)


def _add_replay(add_parser: AddParser) -> None:
    rp = add_parser("replay", help="run the node in-process on a bag, record its outputs, score them against the bag's GT")
    rp.add_argument("bag", help="rosbag2 folder (sqlite3 or mcap)")
    rp.add_argument("--checkpoint", required=True)
    rp.add_argument("--out", required=True, help="bag folder to record the node's outputs into")
    pace = rp.add_mutually_exclusive_group()
    pace.add_argument("--rate", type=float, default=None, help="play at R x recorded speed (the node drops what it cannot keep up with)")
    pace.add_argument("--as-fast-as-possible", action="store_true", help="lock-step: every frame is processed (default)")
    rp.add_argument("--report", default=None, help="metrics JSON (as `axispose eval`, plus latency and node counters)")
    rp.add_argument("--overlays", default=None, help="folder for a few debug overlay PNGs")
    rp.add_argument("--steps", type=int, default=None, help="ddim_steps parameter of the node")
    rp.add_argument("--hypotheses", type=int, default=None, help="hypotheses parameter of the node (AGM samples per object)")
    rp.add_argument("--guidance", type=float, default=None, help="guidance_scale parameter of the node")
    rp.add_argument("--precision", choices=["auto", "float32", "bfloat16"], default=None,
                    help="precision parameter of the node (default: auto, bfloat16 where the CPU has it natively)")  # fmt: skip
    rp.add_argument("--format", choices=["sqlite3", "mcap"], default="mcap", help="storage of the output bag")
    rp.add_argument("--image-topic", default=None, help="Image topic in the bag (default: its only one)")
    rp.add_argument("--camera-info-topic", default=None, help="CameraInfo topic in the bag (default: its only one)")
    rp.add_argument("--odom-topic", default=None, help="Odometry topic in the bag played onto camera_odom (default: its only one, if any)")
    rp.add_argument(
        "--ignore-rois", action="store_true", help="do not play the bag's /roi/<name> boxes: the checkpoint's localiser finds the objects"
    )
    rp.add_argument("--mode", choices=MODES, default=None, help="mode parameter of the node (default: its own, auto)")
    rp.add_argument("--refine", choices=["on", "off"], default=None, help="refine parameter of the node (default: its own, on)")
    rp.add_argument("--redetect-period", type=int, default=None, help="redetect_period parameter of the node (video modes)")
    rp.add_argument("--measure-every", type=int, default=None, help="measure_every parameter of the node (video modes)")
    rp.add_argument("--view-window", type=int, default=None, help="view_window parameter of the node (video_odometry)")
    rp.add_argument("--follow-passes", type=int, default=None, help="follow_passes parameter of the node (video modes)")
    rp.add_argument("--threads", type=int, default=2)
    rp.set_defaults(func=_replay)


def _add_soak(add_parser: AddParser) -> None:
    sk = add_parser("soak", help="the node in its own process on a bag looped at a camera's rate, with faults injected: "
                    "RSS, frames delivered and dropped, faults counted, tracks reset")  # fmt: skip
    sk.add_argument("bag", help="rosbag2 folder with an Image and a CameraInfo topic")
    sk.add_argument("--checkpoint", default=None, help="estimator checkpoint (default: the shipped one)")
    sk.add_argument("--minutes", type=float, default=10.0)
    sk.add_argument("--rate", type=float, default=30.0, help="frames per second sent")
    sk.add_argument("--mode", choices=MODES, default="auto", help="mode parameter of the node")
    sk.add_argument("--view-window", type=int, default=160, help="view_window parameter of the node (video_odometry)")
    sk.add_argument("--follow-passes", type=int, default=0, help="follow_passes parameter of the node (video modes)")
    sk.add_argument("--no-faults", action="store_true", help="the stream alone")
    sk.add_argument("--precision", choices=["auto", "float32", "bfloat16"], default="float32")
    sk.add_argument("--threads", type=int, default=2)
    sk.add_argument("--out", default="out/soak", help="folder for soak.json, rss.png and the node's log")
    sk.set_defaults(func=_soak)


def _add_adapt(add_parser: AddParser) -> None:
    ad = add_parser("adapt", help="adapt a checkpoint to your scene from an unlabeled recording of it (a rosbag or a BOP scene "
                    "folder): its own poses, made consistent, teach the AGM the real look")  # fmt: skip
    ad.add_argument("recording", help="rosbag2 (Image + CameraInfo, Odometry if any) or BOP scene folder (rgb/, scene_camera.json)")
    ad.add_argument("--out", required=True, help="folder for the rounds, the report and OUT/adapted.safetensors")
    ad.add_argument("--checkpoint", default=None, help="estimator checkpoint to adapt (default: the shipped one)")
    ad.add_argument("--models", default=str(SHARED_LMO / "models"), help="the objects' BOP models (default: LM-O's beside the clone)")
    ad.add_argument("--config", default=None, help="YAML of AdaptConfig's fields (axispose_core/adapt/run.py), e.g. config/adapt.yaml")
    ad.add_argument("--rounds", type=int, default=None, help="most rounds (default: the config's)")
    ad.add_argument("--steps", type=int, default=None, help="AGM training steps per round (default: the config's)")
    ad.add_argument("--resume", action="store_true", help="go on with the adaptation in --out")
    ad.add_argument("--max-minutes", type=float, default=None, help="stop (and save) after this much wall time; --resume goes on")
    ad.add_argument("--device", default="auto", choices=["cpu", "cuda", "auto"])
    ad.add_argument("--threads", type=int, default=2)
    ad.add_argument("--image-topic", default=None, help="a bag's Image topic (default: its only one)")
    ad.add_argument("--camera-info-topic", default=None, help="a bag's CameraInfo topic (default: its only one)")
    ad.add_argument("--odom-topic", default=None, help="a bag's Odometry topic of the camera (default: its only one, if any)")
    ad.add_argument("--every", type=int, default=1, help="a bag's every n-th image")
    ad.add_argument("--limit", type=int, default=None, help="a bag's first N images at most")
    ad.set_defaults(func=_adapt)


def main(argv: Sequence[str] | None = None) -> int:
    return core_main(argv, build_ros_parser())


if __name__ == "__main__":
    sys.exit(main())
