"""The 2D localiser: decoding hand-made maps, targets round trip, matching, training, the estimator and eval."""

import argparse
import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import TINY_AGM

from axispose_core.adapt.localiser import AdaptLocaliserConfig, PartlyLabelled, adapt_localiser
from axispose_core.agm.model import AxisGenerator
from axispose_core.camera import crop_transform, instance_crop, project
from axispose_core.checkpoint import CheckpointError, read_checkpoint, stored_half
from axispose_core.cli import main
from axispose_core.config import config_from_dict
from axispose_core.data.bop import BopFormatError
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.synth.config import SurfaceConfig
from axispose_core.estimator import Estimator
from axispose_core.estimator_checkpoint import EstimatorConfig
from axispose_core.localiser.decode import Detection, decode, draw_targets, focal_loss, iou, match
from axispose_core.localiser.model import STRIDE, Localiser, LocaliserConfig, build_localiser
from axispose_core.localiser.scoring import detection_scores, frame_outcome
from axispose_core.localiser.weights import KIND, load_localiser, warm_start
from axispose_core.objects import objects_from_models
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.train.command import score_and_attach
from axispose_core.train.dataset import AxisCropDataset
from axispose_core.train.localiser import LocaliserDataset, LocaliserTrainConfig, localiser_loss, train_localiser
from axispose_core.train.loop import OptimConfig, RunOptions
from axispose_core.train.resume import state_path
from axispose_core.trunks import ResidualBNConfig
from axispose_core.trunks.efficientnet_lite import EfficientNetLiteConfig
from axispose_core.trunks.style_mix import StyleMix

TINY = LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32)))


def test_decode_finds_peaks_with_nms_threshold_offset_and_size():
    heat = torch.zeros(1, 2, 10, 12)
    heat[0, 0, 2, 3] = 0.9
    heat[0, 0, 2, 4] = 0.8  # a neighbour of a higher peak: suppressed
    heat[0, 0, 7, 9] = 0.6
    heat[0, 1, 5, 5] = 0.2  # below the threshold
    size = torch.zeros(1, 2, 10, 12)
    size[0, :, 2, 3] = torch.log(torch.tensor([40.0, 20.0]))
    offset = torch.zeros(1, 2, 10, 12)
    offset[0, :, 2, 3] = torch.tensor([0.25, -0.5])
    (dets,) = decode(heat, size, offset, [1, 5], stride=8, threshold=0.3)
    assert [(d.obj_id, round(d.score, 3)) for d in dets] == [(1, 0.9), (1, 0.6)]
    assert dets[0].center == pytest.approx(((3 + 0.5 + 0.25) * 8, (2 + 0.5 - 0.5) * 8))
    assert dets[0].size == pytest.approx((40.0, 20.0))
    assert dets[0].box == pytest.approx((30 - 20, 16 - 10, 40, 20))
    assert decode(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 4), [1, 5], 8) == [[]]
    with pytest.raises(ValueError, match="heatmap"):
        decode(heat, size, offset, [1], stride=8)


def test_targets_decode_back_to_their_boxes():
    boxes = [(0, (33.0, 21.0, 40.0, 24.0)), (1, (90.5, 60.0, 22.0, 30.0))]
    heat, log_size, offset, mask = draw_targets(boxes, 2, (16, 20), STRIDE)
    assert mask.sum() == 2 and heat.max() == 1.0
    (dets,) = decode(*(torch.from_numpy(a)[None] for a in (heat, log_size, offset)), [1, 5], STRIDE, threshold=0.99)
    got = {d.obj_id: d.box for d in dets}
    assert got[1] == pytest.approx(boxes[0][1], abs=1e-4) and got[5] == pytest.approx(boxes[1][1], abs=1e-4)


def test_weighted_centres_count_more_in_the_loss():
    boxes = [(0, (33.0, 21.0, 40.0, 24.0)), (1, (90.5, 60.0, 22.0, 30.0))]
    heat, _, _, mask = draw_targets(boxes, 2, (16, 20), STRIDE, weights=[1.0, 2.5])
    assert sorted(mask[mask > 0].tolist()) == [1.0, 2.5]
    assert np.array_equal(mask > 0, draw_targets(boxes, 2, (16, 20), STRIDE)[3] > 0)
    with pytest.raises(ValueError, match="weights"):
        draw_targets(boxes, 2, (16, 20), STRIDE, weights=[1.0])
    target, weight = torch.from_numpy(heat)[None], torch.from_numpy(mask)[None, None]
    pred = target.clamp(0.05, 0.95)  # right everywhere but not confident
    pred[0, 1][target[0, 1] == 1] = 0.2  # the second (weighted) centre scores low
    assert focal_loss(pred, target, torch.ones_like(weight)) == pytest.approx(float(focal_loss(pred, target)))
    assert focal_loss(pred, target, weight) > focal_loss(pred, target)


def test_occluded_instances_weigh_by_their_hidden_fraction(frames):
    plain = LocaliserDataset([frames], TINY, min_visib=0.0)
    weighted = LocaliserDataset([frames], TINY, min_visib=0.0, occluded_weight=2.0)
    scene, im_id = weighted.frames[0]
    visib = [info.visib_fract for g, info in zip(scene.gt[im_id], scene.gt_info[im_id], strict=True) if g.obj_id in (1, 5)]
    assert [w for _, _, w in plain.boxes(0)] == [1.0] * len(visib)
    assert [w for _, _, w in weighted.boxes(0)] == pytest.approx([1 + 2 * (1 - v) for v in visib])


def test_surface_varies_the_objects_own_pixels_only(frames):
    """The objects' look varies inside their visible masks and nowhere else; off (the default) draws nothing."""
    looks = LocaliserDataset([frames], TINY, min_visib=0.0, surface=SurfaceConfig(response_prob=1.0, detail_prob=1.0))
    scene, im_id = looks.frames[0]
    rgb = scene.rgb(im_id).astype(np.float32) / 255
    varied = looks._surfaces(np.random.default_rng(0), scene, im_id, rgb.copy())
    masks = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 0 for p in sorted((scene.root / "mask_visib").glob(f"{im_id:06d}_*.png"))]
    known = np.zeros(rgb.shape[:2], bool)
    for k, (gt, _) in enumerate(scene.instances(im_id)):
        known |= masks[k] if gt.obj_id in (1, 5) else False
    changed = np.abs(varied - rgb).max(axis=2) > 1e-6
    assert known.any() and changed.any() and not (changed & ~known).any()
    plain = LocaliserDataset([frames], TINY, min_visib=0.0)
    default = LocaliserDataset([frames], TINY, min_visib=0.0, surface=SurfaceConfig())
    assert torch.equal(plain[0]["image"], default[0]["image"])


def test_the_loss_is_finite_under_bfloat16_autocast(frames):
    """The trunk may train in bfloat16; the heads' sigmoid and the focal loss stay in float32 (in bfloat16 the
    heatmap rounds to 1 and the loss is NaN from the first step)."""
    data = LocaliserDataset([frames], TINY, min_visib=0.0)
    batch = {k: torch.stack([data[i][k] for i in range(2)]) for k in data[0]}
    torch.manual_seed(0)
    model = Localiser(TINY)
    for p in model.heat[-1].parameters():  # a confident heatmap: the case bfloat16 cannot represent
        p.data.fill_(5.0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        heat, _, _ = model(batch["image"])
        loss = localiser_loss(model, batch, LocaliserTrainConfig(localiser=TINY))
    assert heat.dtype == torch.float32 and torch.isfinite(loss)


def test_match_takes_detections_by_score_and_iou():
    assert iou((0, 0, 10, 10), (5, 0, 10, 10)) == pytest.approx(50 / 150)
    gts = [(1, (0, 0, 10, 10)), (1, (100, 100, 10, 10)), (5, (0, 0, 10, 10))]
    dets = [Detection(1, 0.5, (5, 5), (10, 10)), Detection(1, 0.9, (6, 5), (10, 10)), Detection(5, 0.7, (40, 40), (10, 10))]
    assert match(dets, gts) == [1, None, None]  # the better-scoring duplicate wins; the far "5" is a false alarm
    assert match([], gts) == [None, None, None]


def test_frame_outcome_scores_visible_instances_and_spares_detections_of_hidden_ones():
    insts = [(1, (0, 0, 10, 10), 0.9), (1, (100, 100, 10, 10), 0.2), (5, (50, 0, 10, 10), 0.6)]
    dets = [Detection(1, 0.9, (5, 5), (10, 10)), Detection(1, 0.8, (105, 105), (10, 10)), Detection(5, 0.7, (300, 300), (10, 10))]
    found, alarms = frame_outcome(dets, insts, min_visib=0.3)
    assert found == {0: True, 2: False}  # the 0.2-visible instance is not scored...
    assert alarms == [2]  # ...and the detection that found it is no false alarm


@pytest.fixture(scope="module")
def trained(frames, tmp_path_factory):
    torch.manual_seed(0)
    before = Localiser(TINY).eval()
    optim = OptimConfig(steps=150, batch=4, lr=3e-3, warmup=10, workers=0, save_every=1000, ema_decay=0.9)
    cfg = LocaliserTrainConfig(localiser=TINY, optim=optim)
    out = tmp_path_factory.mktemp("det") / "det.safetensors"
    train_localiser(cfg, [frames], out, run=RunOptions(progress=False))
    return before, out


@pytest.mark.slow
def test_training_on_a_tiny_set_increases_recall(frames, trained):
    before, path = trained
    after = load_localiser(path)
    r0 = detection_scores(before, [frames], min_visib=0.3)["recall"]
    r1 = detection_scores(after, [frames], min_visib=0.3)
    assert r1["recall"] > r0 and r1["recall"] >= 0.5
    assert set(r1["objects"]) == {"1", "5"} and r1["ms_per_frame"]["median"] > 0


def test_frames_without_scene_gt_info_need_the_models(frames, tmp_path, lmo_dir, official_like):
    copy = official_like(frames / "000000", tmp_path / "frames" / "000000")
    with pytest.raises(BopFormatError, match="scene_gt_info"):
        detection_scores(Localiser(TINY).eval(), [copy], min_visib=0.3, progress=False)
    with pytest.raises(BopFormatError, match="scene_gt_info"):
        LocaliserDataset([copy], TINY, min_visib=0.1)
    with pytest.raises(BopFormatError, match="scene_gt_info"):  # the AGM's crops, too
        AxisCropDataset([copy], objects_from_models(frames, [1, 5]), 64)
    # With the models, boxes come from them at the GT pose: the same as the files' for every instance.
    real = LocaliserDataset([frames], TINY, min_visib=0.1)
    estimated = LocaliserDataset([copy], TINY, min_visib=0.1, models_dir=lmo_dir / "models")
    assert [b for _, b, _ in estimated.boxes(0)] == [b for _, b, _ in real.boxes(0)]
    crops = AxisCropDataset([copy], objects_from_models(frames, [1, 5]), 64, models_dir=lmo_dir / "models")
    assert len(crops) > 0 and crops[0]["crop"].shape == (3, 64, 64)


def test_a_frame_without_objects_gives_no_detections(trained):
    localiser = load_localiser(trained[1])
    assert localiser.detect(np.full((480, 640, 3), 90, np.uint8)) == []
    with pytest.raises(ValueError, match="uint8"):
        localiser.detect(np.zeros((480, 640), np.float32))


def test_detected_crop_intrinsics_project_the_gt_origin_consistently(frames, trained):
    """A crop cut around a detection: its K' sends the GT origin where the crop's pixel map sends the full-frame pixel,
    and that pixel of the crop shows what the frame shows there."""
    localiser = load_localiser(trained[1])
    scene = BopScene(frames / "000000")
    im_id = scene.image_ids[0]
    rgb = scene.rgb(im_id)
    dets = localiser.detect(rgb, threshold=0.05)
    assert dets
    K = scene.cameras[im_id]
    for d in dets[:3]:
        g = next(g for g in scene.gt[im_id] if g.obj_id == d.obj_id)
        crop = instance_crop(rgb, K, d.box, 64)
        uv_full = project(K, g.t[None])[0]
        expected = (crop_transform(crop.center, crop.side, 64) @ np.append(uv_full, 1.0))[:2]
        np.testing.assert_allclose(project(crop.K_patch, g.t[None])[0], expected, atol=1e-6)
        u, v = np.round(expected).astype(int)
        x, y = np.round(uv_full).astype(int)
        if 2 <= u < 62 and 2 <= v < 62 and 0 <= x < 640 and 0 <= y < 480:
            patch_mean = crop.patch[v - 1 : v + 2, u - 1 : u + 2].reshape(-1, 3).mean(0)
            half = max(1, round(crop.side / 64))
            frame_mean = rgb[y - 2 * half : y + 2 * half + 1, x - 2 * half : x + 2 * half + 1].reshape(-1, 3).mean(0)
            assert np.abs(patch_mean - frame_mean).max() < 40


def test_the_fused_inference_copy_finds_what_the_trained_localiser_finds(frames, trained):
    """BatchNorm folded into the convolutions changes the layers, not the outputs; the original keeps its own."""
    localiser = load_localiser(trained[1])
    keys = set(localiser.state_dict())
    fused = localiser.fused()
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    assert set(localiser.state_dict()) == keys
    scene = BopScene(frames / "000000")
    rgb = scene.rgb(scene.image_ids[0])
    x = localiser.prepare(rgb)
    with torch.inference_mode():
        for a, b in zip(localiser(x), fused(x), strict=True):
            torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
    found, again = localiser.detect(rgb, threshold=0.05), fused.detect(rgb, threshold=0.05)
    assert found and [d.obj_id for d in found] == [d.obj_id for d in again]
    np.testing.assert_allclose([d.box for d in found], [d.box for d in again], atol=1e-2)


def test_a_lite0_localiser_folds_its_batchnorm_too():
    """The ImageNet trunk's layers (TensorFlow padding, depthwise convolutions) fold as the from-scratch trunk's do,
    with BatchNorm statistics and affine parameters far from the identity."""
    torch.manual_seed(0)
    cfg = LocaliserConfig(obj_ids=(1, 5), input_size=(128, 96), trunk=EfficientNetLiteConfig(stages=5, weights="none"), neck=32)
    net = build_localiser(cfg)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    net.eval()
    fused = net.fused()
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    x = torch.randint(0, 256, (2, 3, 96, 128), dtype=torch.uint8)
    with torch.inference_mode():
        for a, b in zip(net(x), fused(x.contiguous(memory_format=torch.channels_last)), strict=True):
            torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


@pytest.fixture(scope="module")
def estimator_with_localiser(frames, trained, tmp_path_factory):
    reader = load_reader(SHIPPED_READER)
    objects = objects_from_models(frames, [1, 5], names={1: "ape", 5: "can"})
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config,
                          objects=tuple(objects), ddim_steps=1)  # fmt: skip
    path = tmp_path_factory.mktemp("est") / "est.safetensors"
    Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(load_localiser(trained[1])).save(path)
    return path


def test_style_mixing_acts_while_the_localiser_trains_and_leaves_a_plain_localiser(frames, tmp_path, monkeypatch):
    calls = []
    forward = StyleMix.forward
    monkeypatch.setattr(StyleMix, "forward", lambda self, x: calls.append(self.training) or forward(self, x))
    cfg = config_from_dict(
        LocaliserTrainConfig,
        {"optim": {"steps": 2, "batch": 2, "warmup": 1, "workers": 0, "save_every": 1000}, "style_mix": {"prob": 1.0, "after": [1, 2]}},
    )
    cfg = replace(cfg, localiser=TINY)
    assert cfg.style_mix.after == (1, 2)
    train_localiser(cfg, [frames], tmp_path / "mixed.safetensors", run=RunOptions(progress=False))
    assert calls.count(True) == 2 * 2  # after two stages, in each of two steps
    trained = load_localiser(tmp_path / "mixed.safetensors")
    assert trained.trunk.style_mix is None
    assert trained.state_dict().keys() == Localiser(TINY).state_dict().keys()


def test_estimator_checkpoint_carries_the_localiser(estimator_with_localiser, frames):
    est = Estimator.load(estimator_with_localiser)
    assert est.localiser is not None and est.config.localiser.obj_ids == (1, 5)
    blank = np.zeros((480, 640, 3), np.uint8)
    assert est.detect(blank) == []
    bare = Estimator(EstimatorConfig(agm=est.config.agm, reader=est.config.reader, objects=est.config.objects), est.agm, est.reader)
    with pytest.raises(ValueError, match="no localiser"):
        bare.detect(blank)
    with pytest.raises(ValueError, match="together"):
        Estimator(est.config, est.agm, est.reader)


def test_a_checkpoint_with_localiser_weights_but_no_config_is_refused(estimator_with_localiser, tmp_path):
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(estimator_with_localiser), framework="pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    cfg = json.loads(meta["config"])
    cfg["localiser"] = None
    save_file(tensors, str(tmp_path / "bad.safetensors"), metadata=meta | {"config": json.dumps(cfg)})
    with pytest.raises(CheckpointError, match="no localiser config"):
        Estimator.load(tmp_path / "bad.safetensors")


@pytest.mark.parametrize("half", [True, False])
def test_attach_keeps_the_precision_the_checkpoint_is_stored_in(estimator_with_localiser, trained, tmp_path, half):
    target = tmp_path / "est.safetensors"
    Estimator.load(estimator_with_localiser).save(target, half=half)
    assert stored_half(target) == half
    assert score_and_attach(argparse.Namespace(out=str(trained[1]), val=None, attach=str(target))) == 0
    assert stored_half(target) == half  # the shipped file stays float16, within its size budget
    attached, trained_weights = Estimator.load(target).localiser.state_dict(), load_localiser(trained[1]).state_dict()
    for key, value in trained_weights.items():
        torch.testing.assert_close(attached[key], value, atol=1e-2 if half else 0, rtol=1e-2 if half else 0)


def test_eval_with_detected_crops_reports_detection_scores(estimator_with_localiser, frames, lmo_dir, tmp_path):
    code = main(["eval", "--checkpoint", str(estimator_with_localiser), "--data", str(frames), "--models", str(lmo_dir / "models_eval"),
                 "--crops", "detect", "--report", str(tmp_path / "r.json"), "--threads", "1"])  # fmt: skip
    assert code == 0
    report = json.loads((tmp_path / "r.json").read_text())
    for entry in report["objects"].values():
        assert 0 <= entry["det_recall"] <= 1 and "det_precision" in entry and entry["n"] > 0
    assert report["config"]["crops"] == "detect"


def test_a_fifth_width_adds_a_stride_32_context_stage():
    deep = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 112), trunk=ResidualBNConfig(widths=(8, 16, 24, 32, 48)))).eval()
    heat, size, offset = deep(torch.zeros(1, 3, 112, 160, dtype=torch.uint8))  # 112 / 32 is not whole: the stage's map is resized back
    assert heat.shape == (1, 2, 14, 20) and size.shape == offset.shape == (1, 2, 14, 20)
    assert any(k.startswith("trunk.stages.4.") for k in deep.state_dict())
    with pytest.raises(ValueError, match="4 or 5 stages"):
        Localiser(LocaliserConfig(obj_ids=(1,), trunk=ResidualBNConfig(widths=(8, 16, 24))))


def test_more_neck_blocks_add_residual_blocks_on_the_fused_map_and_keep_the_outputs_shape():
    one, three = Localiser(TINY).eval(), Localiser(replace(TINY, neck_blocks=3)).eval()
    assert len(three.fuse) == len(one.fuse) + 2
    assert set(one.state_dict()) < set(three.state_dict())  # a one-block localiser's weights still load by name
    frame = torch.zeros(1, 3, 128, 160, dtype=torch.uint8)
    with torch.no_grad():
        assert [t.shape for t in three(frame)] == [t.shape for t in one(frame)]


def test_warm_start_copies_what_matches_and_leaves_the_rest_fresh(trained, estimator_with_localiser):
    source = load_localiser(trained[1]).state_dict()
    torch.manual_seed(1)
    deep = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(*TINY.trunk.widths, 48))))
    fresh = warm_start(deep, trained[1])
    assert fresh and all(k.startswith(("trunk.stages.4.", "fuse32.")) for k in fresh)
    for k, v in deep.state_dict().items():
        if k not in fresh:
            assert torch.equal(v, source[k]), k
    other = Localiser(LocaliserConfig(obj_ids=(5, 1), input_size=(160, 128), trunk=TINY.trunk))
    fresh = warm_start(other, estimator_with_localiser)  # the estimator's copy; objects in another order
    assert fresh and all(k.startswith("heat.") for k in fresh) and "heat.0.0.weight" in fresh
    assert torch.equal(other.state_dict()["trunk.stages.2.0.0.weight"], source["trunk.stages.2.0.0.weight"])


def test_a_warm_started_run_keeps_naming_its_start_when_resumed(frames, trained, tmp_path):
    cfg = LocaliserTrainConfig(localiser=TINY, optim=OptimConfig(steps=2, batch=2, warmup=1, workers=0, save_every=1000))
    out = tmp_path / "warm.safetensors"
    train_localiser(cfg, [frames], out, run=RunOptions(progress=False), init=trained[1])
    assert read_checkpoint(out, KIND, LocaliserConfig)[2]["training"]["init"] == str(trained[1])
    train_localiser(replace(cfg, optim=replace(cfg.optim, steps=3)), [frames], out, run=RunOptions(state_path(out), progress=False))
    record = read_checkpoint(out, KIND, LocaliserConfig)[2]["training"]
    assert record["steps"] == 3 and record["init"] == str(trained[1])


def test_frozen_parts_stay_as_loaded_while_the_box_heads_train(frames, trained, tmp_path):
    """The neck and the heatmap kept as loaded (weights and BatchNorm statistics): what finds the objects stays, the
    size and offset heads learn."""
    optim = OptimConfig(steps=3, batch=2, lr=1e-2, warmup=1, workers=0, save_every=1000, ema_decay=0.0)
    cfg = LocaliserTrainConfig(localiser=TINY, optim=optim, frozen_parts=("fuse", "heat"))
    out = tmp_path / "boxes.safetensors"
    train_localiser(cfg, [frames], out, run=RunOptions(progress=False), init=trained[1])
    before, after = load_localiser(trained[1]).state_dict(), load_localiser(out).state_dict()
    assert not all(torch.equal(before[k], after[k]) for k in before if k.startswith(("size.", "offset.")))
    assert all(torch.equal(before[k], after[k]) for k in before if k.startswith(("fuse.", "heat.")))
    with pytest.raises(ValueError, match="fuse32"):
        Localiser(TINY).freeze_parts(("fuse32",))  # a 4-stage trunk has no stride-32 fusion


def test_load_localiser_reads_an_estimator_checkpoint_and_refuses_one_without_a_localiser(trained, estimator_with_localiser):
    own, carried = load_localiser(trained[1]), load_localiser(estimator_with_localiser)
    assert carried.config == own.config and not carried.training
    for k, v in own.state_dict().items():
        assert torch.equal(carried.state_dict()[k], v), k
    with pytest.raises(CheckpointError, match="'tbm_reader' checkpoint without a localiser"):
        load_localiser(SHIPPED_READER)


def test_warm_start_from_a_checkpoint_without_a_localiser_is_refused():
    with pytest.raises(CheckpointError, match="without a localiser"):
        warm_start(Localiser(TINY), SHIPPED_READER)


def _partly_labelled(frames: Path, dst: Path, keep: int) -> Path:
    """A copy of `frames`' scene whose labels name object `keep` alone (as pseudo-labels name what was accepted)."""
    scene = next(p for p in sorted(frames.iterdir()) if (p / "scene_gt.json").exists())
    shutil.copytree(scene, dst, ignore=shutil.ignore_patterns("mask", "mask_visib", "scene_gt_info.json", "depth"))
    gt = json.loads((dst / "scene_gt.json").read_text())
    (dst / "scene_gt.json").write_text(json.dumps({k: [e for e in v if e["obj_id"] == keep] for k, v in gt.items()}))
    return dst


def test_a_class_a_frame_does_not_label_is_no_negative_there():
    target = torch.zeros(1, 2, 6, 8)
    target[0, 0, 2, 3] = 1.0
    pred = torch.full((1, 2, 6, 8), 0.3)
    louder = pred.clone()
    louder[0, 1] = 0.9  # the unlabelled class fires everywhere
    known = torch.tensor([[1.0, 0.0]])
    assert torch.allclose(focal_loss(pred, target, known=known), focal_loss(louder, target, known=known))
    assert focal_loss(louder, target) > focal_loss(pred, target)
    louder[0, 0, 0, 0] = 0.9  # the labelled class fires away from its object: still a negative
    assert focal_loss(louder, target, known=known) > focal_loss(pred, target, known=known)


def test_a_partly_labelled_frame_knows_only_its_labelled_objects(frames, tmp_path, lmo_dir):
    labels = _partly_labelled(frames, tmp_path / "labels", keep=1)
    partial = PartlyLabelled([labels], TINY, 0.1, models_dir=lmo_dir / "models")
    full = LocaliserDataset([frames], TINY, 0.1)
    assert all(partial.known(i).tolist() == [1.0, 0.0] for i in range(len(partial)))
    assert torch.equal(partial[0]["known"], torch.tensor([1.0, 0.0])) and torch.equal(full[0]["known"], torch.ones(2))
    assert all(c == 0 for i in range(len(partial)) for c, _, _ in partial.boxes(i))


def test_the_adapted_localiser_is_written_into_the_whole_estimator(estimator_with_localiser, frames, tmp_path, lmo_dir):
    labels = _partly_labelled(frames, tmp_path / "labels", keep=1)
    optim = OptimConfig(steps=4, batch=2, lr=1e-3, warmup=1, workers=0, save_every=1000, val_every=1000)
    source = Estimator.load(estimator_with_localiser)

    def adapted(name: str, **changes) -> Estimator:
        cfg = AdaptLocaliserConfig(optim=optim, val_frames=2, **changes)
        out = tmp_path / f"{name}.safetensors"
        assert adapt_localiser(estimator_with_localiser, labels, [frames], lmo_dir / "models", out, cfg, RunOptions(progress=False)) == 4
        return Estimator.load(out)

    tuned, kept = adapted("tuned"), adapted("kept", blend=0.0)
    for est in (tuned, kept):
        assert all(torch.equal(a, b) for a, b in zip(est.agm.state_dict().values(), source.agm.state_dict().values(), strict=True))
        assert "adapt_localiser" in est.config.training
    moved = [
        not torch.allclose(a, b) for a, b in zip(tuned.localiser.state_dict().values(), source.localiser.state_dict().values(), strict=True)
    ]
    assert any(moved)
    assert all(
        torch.allclose(a, b, atol=1e-3)
        for a, b in zip(kept.localiser.state_dict().values(), source.localiser.state_dict().values(), strict=True)
        if a.is_floating_point()
    )  # blend 0: the source's weights (its counters the fine-tune's)
