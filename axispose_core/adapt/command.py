"""The body of `axispose adapt` once the recording is a BOP scene folder (`axispose_ros.cli` writes a bag out as
one first): settings from the command line and an optional YAML of `AdaptConfig`'s fields, the run, and what it
prints."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

from axispose_core.adapt.recording import Recording, RecordingError, read_recording
from axispose_core.adapt.run import Adaptation, AdaptConfig, AdaptError
from axispose_core.checkpoint import CheckpointError
from axispose_core.config import ConfigError, config_from_dict, yaml_mapping
from axispose_core.train.loop import RunOptions


@dataclass(frozen=True)
class AdaptRequest:
    """What the command line asks for."""

    recording: Path
    out: Path
    checkpoint: Path
    models: Path
    config: str | None = None
    """A YAML file (or inline YAML) of AdaptConfig's fields; None: the defaults."""
    rounds: int | None = None
    steps: int | None = None
    resume: bool = False
    max_minutes: float | None = None
    device: str = "auto"
    progress: bool = True


def adapt_config(request: AdaptRequest) -> AdaptConfig:
    """The YAML's fields over the defaults, then --rounds and --steps."""
    try:
        data = yaml_mapping(request.config, empty_ok=True) if request.config else {}
    except ConfigError as err:
        raise ConfigError(f"--config: {err}") from err
    cfg = config_from_dict(AdaptConfig, data, f"--config {request.config}")
    if request.rounds is not None:
        cfg = dataclasses.replace(cfg, rounds=request.rounds)
    if request.steps is not None:
        train = cfg.train
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(train, optim=dataclasses.replace(train.optim, steps=request.steps)))
    return cfg


def run_adapt(request: AdaptRequest, recording: Recording | None = None) -> int:
    """Run (or resume) the adaptation; 0 when the adapted checkpoint is written, 3 when the time cap stopped it
    (the same command with --resume goes on), 2 with one line on stderr when it cannot start."""
    try:
        recording = recording or read_recording(request.recording)
        if not request.models.is_dir():
            raise AdaptError(f"{request.models}: no models folder (the objects' BOP models, for the crop stream and the labels)")
        cfg = adapt_config(request)
        run = RunOptions(device=request.device, max_minutes=request.max_minutes, progress=request.progress)
        adaptation = Adaptation(recording, request.checkpoint, request.models, request.out, cfg, run, resume=request.resume)
    except (AdaptError, RecordingError, CheckpointError, ConfigError, ValueError, FileNotFoundError) as err:
        print(f"axispose adapt: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(f"adapting {request.checkpoint} on {len(recording.frames)} frames of {recording.root} "
          f"({'with' if recording.has_odometry else 'without'} odometry) into {request.out}")  # fmt: skip
    try:
        final = adaptation.run(progress=request.progress)
    except AdaptError as err:
        print(f"axispose adapt: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    if final is None:
        print(f"stopped at the time cap; `axispose adapt ... --out {request.out} --resume` goes on")
        return 3
    print(f"adapted checkpoint: {final}; report: {request.out / 'report.json'}")
    return 0
