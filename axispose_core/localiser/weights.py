"""Trained localiser weights: loaded from a localiser's own checkpoint or an estimator's, and copied into a new
network to warm-start it."""

from __future__ import annotations

from pathlib import Path

from axispose_core.checkpoint import ESTIMATOR, CheckpointError, load_state, read_checkpoint, read_metadata
from axispose_core.localiser.model import Localiser, LocaliserConfig, build_localiser

KIND = "localiser"


def load_localiser(path: str | Path, device: str = "cpu") -> Localiser:
    """A trained localiser in eval mode, from its own checkpoint or from an estimator checkpoint that carries one
    (without building the estimator's AGM)."""
    kind = read_metadata(path, None)["kind"]
    config: LocaliserConfig | None = None
    if kind == KIND:
        config, states, _ = read_checkpoint(path, KIND, LocaliserConfig)
    elif kind == ESTIMATOR:  # its localiser alone: an estimator of an older AGM version still lends its localiser
        config, states, _ = read_checkpoint(path, ESTIMATOR, LocaliserConfig, section="localiser")
    if config is None:
        raise CheckpointError(f"{path}: a {kind!r} checkpoint without a localiser")
    model = build_localiser(config)
    load_state(model, states.get("localiser", {}), str(path))
    return model.to(device).eval()


def warm_start(model: Localiser, path: str | Path) -> list[str]:
    """Copy into `model` the weights of a trained localiser (`load_localiser`: its own checkpoint, or an
    estimator's that carries one) wherever names and shapes match, so a wider or deeper localiser, or one for other
    objects, need not relearn what the trained one knows. The heatmap head is copied only for the same objects in
    the same order (its channels are the objects). Returns the tensor names left at their fresh initialisation."""
    source = load_localiser(path)
    same_objects = source.config.obj_ids == model.config.obj_ids
    own = model.state_dict()
    take = {
        k: v for k, v in source.state_dict().items() if k in own and v.shape == own[k].shape and (same_objects or not k.startswith("heat."))
    }
    model.load_state_dict(take, strict=False)
    return sorted(set(own) - set(take))
