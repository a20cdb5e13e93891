"""The localiser's second stage: crop geometry, labels, rescoring, checkpoints, and training on a tiny set."""

import csv
from dataclasses import replace

import numpy as np
import pytest
import torch

from axispose_core.agm.denoiser import DenoiserConfig
from axispose_core.agm.model import AGMConfig, AxisGenerator
from axispose_core.checkpoint import read_checkpoint, save_checkpoint
from axispose_core.cli import main
from axispose_core.data.bop import BopScene
from axispose_core.data.objects import objects_from_models
from axispose_core.detect.model import Localiser, LocaliserConfig
from axispose_core.detect.verifier import Verifier, VerifierConfig, box_crops, crops_tensor
from axispose_core.estimator import Estimator, EstimatorConfig
from axispose_core.tbm.reader import SHIPPED_READER, load_reader
from axispose_core.train.detector import KIND, load_localiser
from axispose_core.train.resume import state_path
from axispose_core.train.verifier import CropDataset, VerifierTrainConfig, box_label, mine_crops, train_verifier

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
    cfg = EstimatorConfig(agm=AGMConfig(denoiser=DenoiserConfig(channels=8, multipliers=(1, 2), groups=4)), reader=reader.config,
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
    crops, labels = mine_crops(load_localiser(localiser_path), [frames], cfg, progress=False)
    assert len(crops) == len(labels) > 50 and crops.shape[1:] == (32, 32, 3)
    assert set(np.unique(labels)) == {0, 1, 2}  # both objects and "nothing"
    out = tmp_path / "ver.safetensors"

    def accuracy(verifier: Verifier) -> float:
        with torch.inference_mode():
            return float((verifier(crops_tensor(crops)).argmax(1).numpy() == labels).mean())

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
    cfg = EstimatorConfig(agm=AGMConfig(denoiser=DenoiserConfig(channels=8, multipliers=(1, 2), groups=4)), reader=reader.config,
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


def test_training_crops_shift_within_bounds_and_repeat_under_a_seed():
    crops = np.zeros((2, 16, 16, 3), np.uint8)
    crops[:, 6:10, 6:10] = 255  # a bright square in the middle
    labels = np.array([0, 2])
    still, moved = CropDataset(crops, labels, seed=1), CropDataset(crops, labels, seed=1, shift=3)
    a, b = still[0], moved[0]
    assert a["image"].shape == b["image"].shape == (3, 16, 16) and a["image"].dtype == torch.float32 and int(b["label"]) == 0
    bright = lambda item: np.argwhere(item["image"][0].numpy() > item["image"][0].numpy().mean())  # noqa: E731
    assert torch.equal(moved[0]["image"], b["image"])  # the same (seed, epoch, index), the same crop
    offsets = []
    for epoch in range(6):
        moved.epoch = still.epoch = epoch
        offsets.append(bright(moved[0]).mean(0) - bright(still[0]).mean(0))
    assert np.abs(offsets).max() <= 3 and np.abs(offsets).max() >= 1
