"""The localiser's second stage: crop geometry, labels, box deltas, rescoring and refining, checkpoints, and
training on a tiny set."""

import csv
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import TINY_AGM

from axispose_core.agm.model import AxisGenerator
from axispose_core.checkpoint import read_checkpoint, save_checkpoint
from axispose_core.cli import main
from axispose_core.data.bop import BopScene
from axispose_core.data.objects import objects_from_models
from axispose_core.detect.model import Localiser, LocaliserConfig
from axispose_core.detect.verifier import (
    DELTA_SCALE,
    MAX_LOG_SCALE,
    Verifier,
    VerifierConfig,
    apply_deltas,
    box_crops,
    box_deltas,
    crops_tensor,
)
from axispose_core.estimator import Estimator, EstimatorConfig
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.train.detector import KIND, load_localiser
from axispose_core.train.resume import state_path
from axispose_core.train.verifier import (
    IGNORE,
    CropDataset,
    MinedCrops,
    VerifierTrainConfig,
    box_label,
    mine_crops,
    refine_target,
    train_verifier,
)

TINY = LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), channels=(8, 16, 24, 32))
VTINY = VerifierConfig(size=32, channels=(8, 16, 16, 32), candidates=0.05)


def test_box_crops_stretch_the_padded_box_onto_the_square_exactly():
    image = np.zeros((100, 200, 3), np.uint8)
    image[20:60, 50:130] = 255  # the box (50, 20, 80, 40), pixel edges on whole numbers
    tight, outside = box_crops(image, [(50, 20, 80, 40), (500, 500, 30, 30)], 32, 1.0)
    assert tight.min() == 255 and outside.max() == 0  # outside the frame: black
    padded = box_crops(image, [(50, 20, 80, 40)], 32, 2.0)[0]
    expected = np.zeros((32, 32, 3), np.uint8)
    expected[8:24, 8:24] = 255  # twice the box: the box is the middle half, to the pixel
    assert np.array_equal(padded, expected)
    x = crops_tensor(np.stack([tight, expected]))
    assert x.shape == (2, 3, 32, 32) and x.min() == -1 and x.max() == 1


def test_box_labels_follow_the_instance_a_box_frames_not_the_object_it_claims():
    insts = [(1, (0.0, 0.0, 10.0, 10.0), 0.9), (5, (50.0, 0.0, 10.0, 10.0), 0.05), (7, (100.0, 0.0, 10.0, 10.0), 0.9)]
    classes = {1: 0, 5: 1}
    assert box_label((0, 0, 10, 10), insts, classes, 0.1) == 0
    assert box_label((1, 0, 10, 10), insts, classes, 0.1) == 0  # IoU 0.82
    assert box_label((5, 0, 10, 10), insts, classes, 0.1) == 2  # IoU 1/3: a poor box is "nothing"
    assert box_label((3, 0, 10, 10), insts, classes, 0.1) == 0  # IoU 0.54
    assert box_label((4, 0, 10, 10), insts, classes, 0.1) is None  # IoU 0.43: neither
    assert box_label((50, 0, 10, 10), insts, classes, 0.1) is None  # an instance 5 % visible: not used
    assert box_label((100, 0, 10, 10), insts, classes, 0.1) is None  # an object the localiser does not know
    assert box_label((300, 300, 10, 10), insts, classes, 0.1) == 2


def test_box_deltas_take_a_box_to_its_target_and_back():
    box, target = (10.0, 20.0, 40.0, 30.0), (18.0, 11.0, 55.0, 24.0)
    d = box_deltas(box, target)
    np.testing.assert_allclose(d, [(45.5 - 30) / 40, (23 - 35) / 30, np.log(55 / 40), np.log(24 / 30)], rtol=1e-6)
    np.testing.assert_allclose(apply_deltas(box, d), target, rtol=1e-5)
    assert apply_deltas(box, np.zeros(4)) == box
    grown = apply_deltas(box, np.array([0.0, 0.0, 9.0, -9.0]))  # absurd scales are clipped
    np.testing.assert_allclose(grown[2:], (40 * np.exp(MAX_LOG_SCALE), 30 * np.exp(-MAX_LOG_SCALE)), rtol=1e-6)
    np.testing.assert_allclose((grown[0] + grown[2] / 2, grown[1] + grown[3] / 2), (30, 35))  # about the same centre


def test_refine_targets_are_the_claimed_objects_best_instance():
    insts = [(1, (0.0, 0.0, 10.0, 10.0), 0.9), (1, (6.0, 0.0, 10.0, 10.0), 0.9), (5, (0.0, 0.0, 10.0, 10.0), 0.05)]
    assert refine_target((5, 0, 10, 10), 1, insts, 0.25, 0.1) == (6.0, 0.0, 10.0, 10.0)  # IoU 0.82 beats 0.33
    assert refine_target((-2, 0, 10, 10), 1, insts, 0.25, 0.1) == (0.0, 0.0, 10.0, 10.0)
    assert refine_target((-6, 0, 10, 10), 1, insts, 0.25, 0.1) == (0.0, 0.0, 10.0, 10.0)  # IoU 1/4: at the bound
    assert refine_target((-7, 0, 10, 10), 1, insts, 0.25, 0.1) is None  # IoU 3/17
    assert refine_target((0, 0, 10, 10), 5, insts, 0.25, 0.1) is None  # its object's instance is 5 % visible
    assert refine_target((0, 0, 10, 10), None, insts, 0.25, 0.1) is None  # a background box


@pytest.fixture(scope="module")
def localiser_path(tmp_path_factory):
    """An untrained localiser: its CenterNet prior (0.1 everywhere) gives peaks all over a frame to verify."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("loc") / "loc.safetensors"
    save_checkpoint(path, KIND, TINY, {"localiser": Localiser(TINY).eval()})
    return path


def _rigged(favour: int) -> Verifier:
    """A verifier whose answer is class `favour` whatever the crop."""
    verifier = Verifier(VTINY, 2).eval()
    with torch.no_grad():
        verifier.head[-1].weight.zero_()
        verifier.head[-1].bias.copy_(torch.tensor([-10.0, -10.0, -10.0]))
        verifier.head[-1].bias[favour] = 10.0
    return verifier


def test_rescoring_keeps_the_boxes_and_replaces_the_scores(frames, localiser_path):
    plain = load_localiser(localiser_path)
    rgb = BopScene(frames / "000000").rgb(0)
    peaks = plain.detect(rgb, threshold=0.05)
    assert {d.obj_id for d in peaks} == {1, 5}
    neutral = plain.with_verifier(Verifier(replace(VTINY, weight=0.0), 2))
    assert neutral.detect(rgb, threshold=0.05) == peaks  # weight 0: the heatmap's own scores
    assert plain.with_verifier(_rigged(2)).detect(rgb) == []  # "nothing" everywhere: no detections, not an error
    ones = plain.with_verifier(_rigged(0)).detect(rgb, threshold=0.5)
    assert ones and {d.obj_id for d in ones} == {1} and min(d.score for d in ones) > 0.99
    assert {d.box for d in ones} == {d.box for d in peaks if d.obj_id == 1}
    assert plain.with_verifier(_rigged(0)).with_verifier(None).config == plain.config


def test_a_refiner_moves_each_box_by_its_objects_deltas_and_keeps_the_scores(frames, localiser_path):
    plain = load_localiser(localiser_path)
    rgb = BopScene(frames / "000000").rgb(0)
    cfg = replace(VTINY, weight=0.0, refine=True)
    refiner = Verifier(cfg, 2).eval()
    shift = {1: np.array([0.3, -0.2, 0.4, 0.0]), 5: np.array([-0.1, 0.0, 0.0, -0.6])}  # box deltas per object
    with torch.no_grad():
        refiner.head[-1].weight.zero_()
        refiner.head[-1].bias.copy_(torch.tensor([0.0, 0.0, 0.0, *(shift[1] / DELTA_SCALE), *(shift[5] / DELTA_SCALE)]))
    peaks = plain.detect(rgb, threshold=0.1)
    refined = plain.with_verifier(refiner).detect(rgb, threshold=0.1)
    assert len(refined) == len(peaks) > 0 and [d.score for d in refined] == [d.score for d in peaks]
    for p, r in zip(peaks, refined, strict=True):
        assert r.obj_id == p.obj_id
        np.testing.assert_allclose(r.box, apply_deltas(p.box, shift[p.obj_id]), rtol=1e-5, atol=1e-3)


def test_a_verifier_travels_in_the_localiser_and_estimator_checkpoints(frames, localiser_path, tmp_path):
    torch.manual_seed(3)
    verifier = Verifier(VTINY, 2).eval()
    both = load_localiser(localiser_path).with_verifier(verifier)
    save_checkpoint(tmp_path / "loc.safetensors", KIND, both.config, {"localiser": both})
    again = load_localiser(tmp_path / "loc.safetensors")
    assert again.config.verifier == VTINY
    for k, v in both.state_dict().items():
        assert torch.equal(again.state_dict()[k], v), k
    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config,
                          objects=tuple(objects_from_models(frames, [1, 5])), ddim_steps=1)  # fmt: skip
    Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(again).save(tmp_path / "est.safetensors")
    est = Estimator.load(tmp_path / "est.safetensors")
    rgb = BopScene(frames / "000000").rgb(1)
    found = again.detect(rgb, threshold=0.05)
    fused = est.detect(rgb, threshold=0.05)  # the BatchNorm-folded copy, verifier included
    assert found and [d.obj_id for d in found] == [d.obj_id for d in fused]
    np.testing.assert_allclose([d.score for d in found], [d.score for d in fused], atol=1e-4)


def test_training_on_a_tiny_set_teaches_the_verifier_its_crops(frames, localiser_path, tmp_path):
    cfg = VerifierTrainConfig(verifier=VTINY, steps=120, batch=32, lr=3e-3, warmup=10, frame_stride=1, save_every=1000,
                              val_every=60, val_frames=2, ema_decay=0.9)  # fmt: skip
    mined = mine_crops(load_localiser(localiser_path), [frames], cfg, progress=False)
    crops, labels = mined.crops, mined.labels
    assert len(crops) == len(labels) > 50 and crops.shape[1:] == (32, 32, 3) and (mined.box_obj == -1).all()
    assert set(np.unique(labels)) == {0, 1, 2}  # both objects and "nothing"
    out = tmp_path / "ver.safetensors"

    def accuracy(verifier: Verifier) -> float:
        with torch.inference_mode():
            return float((verifier(crops_tensor(crops))[0].argmax(1).numpy() == labels).mean())

    torch.manual_seed(cfg.seed)
    before = accuracy(Verifier(VTINY, 2).eval())
    assert train_verifier(cfg, localiser_path, [frames], out, val_data=[frames], progress=False) == 120
    trained = load_localiser(out)
    majority = np.bincount(labels).max() / len(labels)
    assert accuracy(trained.verifier) > max(before, majority) + 0.1
    _, _, meta = read_checkpoint(out, KIND, LocaliserConfig)
    assert meta["training"]["init"] == str(localiser_path) and trained.config.verifier == VTINY
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert [r["step"] for r in rows if r["val_recall"]] == ["60", "120"]

    cache = tmp_path / "ver.safetensors.crops.npz"
    mined_at = cache.stat().st_mtime_ns
    assert train_verifier(replace(cfg, steps=130), localiser_path, [frames], out, resume=state_path(out), progress=False) == 130
    assert cache.stat().st_mtime_ns == mined_at  # the resumed run read the crops it had mined
    torch.manual_seed(1)
    other = tmp_path / "other_localiser.safetensors"
    save_checkpoint(other, KIND, TINY, {"localiser": Localiser(TINY).eval()})  # same config, other weights
    train_verifier(replace(cfg, steps=1), other, [frames], out, progress=False)
    assert cache.stat().st_mtime_ns != mined_at  # its peaks are other boxes: mined again


def test_cli_trains_a_verifier_and_attaches_it(frames, localiser_path, tmp_path):
    import yaml

    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config,
                          objects=tuple(objects_from_models(frames, [1, 5])), ddim_steps=1)  # fmt: skip
    est_path = tmp_path / "est.safetensors"
    Estimator(cfg, AxisGenerator(cfg.agm), reader).with_localiser(load_localiser(localiser_path)).save(est_path)
    config = tmp_path / "v.yaml"
    config.write_text(yaml.safe_dump({"steps": 3, "batch": 8, "warmup": 1, "frame_stride": 2, "save_every": 100,
                                      "verifier": {"size": 32, "channels": [8, 16, 16, 32]}}))  # fmt: skip
    out = tmp_path / "v.safetensors"
    code = main(["train-verifier", "--localiser", str(est_path), "--data", str(frames), "--out", str(out), "--config", str(config),
                 "--attach", str(est_path), "--threads", "1"])  # fmt: skip
    assert code == 0
    attached = Estimator.load(est_path)
    assert attached.config.localiser.verifier == VerifierConfig(size=32, channels=(8, 16, 16, 32))
    assert torch.equal(attached.localiser.verifier.head[-1].bias, load_localiser(out).verifier.head[-1].bias)


def test_training_on_a_tiny_set_teaches_the_refiner_its_boxes(frames, localiser_path, tmp_path):
    cfg = VerifierTrainConfig(verifier=replace(VTINY, weight=0.0, refine=True), steps=150, batch=32, lr=3e-3, warmup=10,
                              frame_stride=1, save_every=1000, ema_decay=0.9, jitter_per_instance=4)  # fmt: skip
    mined = mine_crops(load_localiser(localiser_path), [frames], cfg, progress=False)
    rows = mined.box_obj >= 0
    assert rows.sum() > 30 and set(mined.box_obj[rows]) == {0, 1} and (mined.labels[rows] == IGNORE).any()
    assert (mined.labels[~rows] != IGNORE).all()  # every crop trains something

    def box_error(verifier: Verifier) -> float:
        with torch.inference_mode():
            deltas = verifier(crops_tensor(mined.crops[rows]))[1].numpy()[np.arange(rows.sum()), mined.box_obj[rows]]
        return float(np.abs(deltas * DELTA_SCALE - mined.deltas[rows]).mean())

    out = tmp_path / "refiner.safetensors"
    assert train_verifier(cfg, localiser_path, [frames], out, progress=False) == 150
    trained = load_localiser(out)
    assert trained.config.verifier.refine
    assert box_error(trained.verifier) < 0.6 * float(np.abs(mined.deltas[rows]).mean())  # better than keeping the boxes


def test_shifted_training_crops_move_their_box_targets_with_them():
    image = np.zeros((200, 200, 3), np.uint8)
    image[100:112, 88:104] = 255  # the object: (88, 100, 16, 12), well inside the crop of the box below
    box, pad, side = (70.0, 95.0, 40.0, 30.0), 1.5, 32
    mined = MinedCrops(box_crops(image, [box], side, pad), np.array([0]), np.array([0]), box_deltas(box, (88, 100, 16, 12))[None])
    moved = CropDataset(mined, seed=4, shift=3, pad=pad)
    rows, cols = np.mgrid[0:side, 0:side] + 0.5  # continuous crop coordinates of the pixel centres
    for epoch in range(5):
        moved.epoch = epoch
        item = moved[0]
        weight = item["image"][0].numpy() - item["image"][0].numpy().min()
        centre = np.array([(cols * weight).sum(), (rows * weight).sum()]) / weight.sum()
        seen = (centre - side / 2) * pad / side  # the object's centre from the crop's, in box widths and heights
        np.testing.assert_allclose(item["deltas"][:2].numpy(), seen, atol=0.1 * pad / side)
        np.testing.assert_array_equal(item["deltas"][2:].numpy(), mined.deltas[0, 2:])


def test_training_crops_shift_within_bounds_and_repeat_under_a_seed():
    crops = np.zeros((2, 16, 16, 3), np.uint8)
    crops[:, 6:10, 6:10] = 255  # a bright square in the middle
    labels = np.array([0, 2])
    mined = MinedCrops(crops, labels, np.array([-1, -1]), np.zeros((2, 4), np.float32))
    still, moved = CropDataset(mined, seed=1), CropDataset(mined, seed=1, shift=3)
    a, b = still[0], moved[0]
    assert a["image"].shape == b["image"].shape == (3, 16, 16) and a["image"].dtype == torch.float32 and int(b["label"]) == 0
    bright = lambda item: np.argwhere(item["image"][0].numpy() > item["image"][0].numpy().mean())  # noqa: E731
    assert torch.equal(moved[0]["image"], b["image"])  # the same (seed, epoch, index), the same crop
    offsets = []
    for epoch in range(6):
        moved.epoch = still.epoch = epoch
        offsets.append(bright(moved[0]).mean(0) - bright(still[0]).mean(0))
    assert np.abs(offsets).max() <= 3 and np.abs(offsets).max() >= 1
