"""`axispose adapt` (adapt/): the recording it reads, the candidates' log and its resume, labels written as BOP and
refined on the frame, the real crops in the stream's form and their mixed batches, and a whole round on rendered
frames with the shipped checkpoint: end to end, resumed after an interruption to the same weights, and refusals."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from axispose_core.adapt.command import AdaptRequest, adapt_config, run_adapt
from axispose_core.adapt.crops import KEYS, LabelledCrops, mixed_batches
from axispose_core.adapt.labels import FillConfig, Label, label_frame, write_labels
from axispose_core.adapt.localiser import AdaptLocaliserConfig, RenderedFrames
from axispose_core.adapt.pseudo import PoseSettings, pose_frames, read_candidates
from axispose_core.adapt.recording import RecordingError, read_recording
from axispose_core.adapt.run import ADAPTED, AGM, Adaptation, AdaptConfig, AdaptError, object_geometry
from axispose_core.adapt.scene import ConsistencyConfig, Prediction
from axispose_core.adapt.search import SearchConfig
from axispose_core.adapt.train import AdaptTrainConfig, blend
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.synth.config import CameraPathConfig, PhotometricConfig, StreamConfig, SynthConfig
from axispose_core.data.synth.stream import CropStream
from axispose_core.estimator import SHIPPED_ESTIMATOR, Estimator
from axispose_core.localiser.decode import Detection
from axispose_core.metrics import proj
from axispose_core.objects import lmo_objects
from axispose_core.refine.config import RefineConfig
from axispose_core.refine.refiner import ContourRefiner
from axispose_core.train.loop import OptimConfig, RunOptions
from axispose_core.train.resume import state_path

OBJECTS = (1, 5, 6)


@pytest.fixture(scope="module")
def recording(tmp_path_factory, lmo_dir) -> Path:
    """Four rendered frames of a camera moving past three LM-O objects (BOP layout, the truth in scene_gt.json)."""
    from axispose_core.data.synth.generate import generate

    out = tmp_path_factory.mktemp("recording")
    cfg = SynthConfig(seed=5, scenes=1, images_per_scene=4, objects=OBJECTS, camera_path=CameraPathConfig(orbit_deg=6.0))
    generate(cfg, lmo_dir / "models", out, progress=False)
    return out / "000000"


def test_a_recording_is_its_images_and_cameras_never_its_labels(recording, tmp_path):
    rec = read_recording(recording)
    truth = BopScene(recording)
    assert [f.im_id for f in rec.frames] == truth.image_ids and rec.has_odometry
    assert np.array_equal(rec.frames[0].rgb(), truth.rgb(truth.image_ids[0]))
    R_w2c, t_w2c = truth.camera_poses[rec.frames[1].im_id]
    assert np.allclose(rec.frames[1].camera[:3, :3], R_w2c.T) and np.allclose(rec.frames[1].camera[:3, 3], -R_w2c.T @ t_w2c)
    copy = tmp_path / "copy"
    (copy / "rgb").mkdir(parents=True)
    cams = json.loads((recording / "scene_camera.json").read_text())
    (copy / "scene_camera.json").write_text(json.dumps({k: {"cam_K": v["cam_K"]} for k, v in cams.items()}))
    (copy / "scene_gt.json").write_text("not json: never read")
    for f in rec.frames[:2]:
        (copy / "rgb" / f.path.name).write_bytes(f.path.read_bytes())
    copied = read_recording(copy)
    assert len(copied.frames) == 2 and not copied.has_odometry
    (tmp_path / "empty").mkdir()
    for bad, why in ((tmp_path / "none", "no such folder"), (tmp_path / "empty", "no scene_camera.json")):
        with pytest.raises(RecordingError, match=why):
            read_recording(bad)
    (copy / "rgb" / rec.frames[0].path.name).unlink()
    (copy / "rgb" / rec.frames[1].path.name).unlink()
    with pytest.raises(RecordingError, match="none of the"):
        read_recording(copy)


class _Finder:
    """An estimator's `find` that poses every frame's object 1 at a fixed pose, counting its calls."""

    calls = 0

    def find(self, image, K, threshold=None, options=None):
        from axispose_core.pose_estimate import Found, PoseEstimate

        self.calls += 1
        pose = PoseEstimate(1, np.eye(3), np.array([0.0, 0.0, 0.8]), True, "", np.zeros((4, 4, 3)), K, (0.0, 0.0), 1.0,
                            refined=True, contour_lines=0.8, contour_agreement=0.9)  # fmt: skip
        return Found([Detection(1, 0.9, (320.0, 240.0), (50.0, 60.0))], [pose])


def test_the_candidates_log_resumes_where_it_stopped(recording, tmp_path):
    rec = read_recording(recording)
    log = tmp_path / "candidates.jsonl"
    finder = _Finder()
    first = pose_frames(finder, rec.frames[:2], PoseSettings(), log)
    with open(log, "a") as f:
        f.write('{"im_id": 99, "candidates": [')  # a line cut off by a kill
    finder.calls = 0
    again = pose_frames(finder, rec.frames, PoseSettings(), log)
    assert finder.calls == len(rec.frames) - 2 and sorted(again) == [f.im_id for f in rec.frames]
    for im_id, cs in first.items():
        assert [c.to_json() for c in cs] == [c.to_json() for c in again[im_id]]
    c = again[rec.frames[0].im_id][0]
    assert c.refined and c.agreement == 0.9 and c.box == (295.0, 210.0, 50.0, 60.0)
    assert sorted(read_candidates(log)) == sorted(again)  # the cut line was dropped when the log was rewritten


def _truth_labels(recording: Path) -> list[Label]:
    truth = BopScene(recording)
    return [Label(i, g.obj_id, g.R, g.t, "checked", 0.9) for i in truth.image_ids for g in truth.gt[i]]


def test_labels_are_a_bop_folder_and_their_crops_the_streams_samples(recording, tmp_path, lmo_dir):
    rec = read_recording(recording)
    labels = [lab for lab in _truth_labels(recording) if lab.im_id != rec.frames[3].im_id]
    folder = write_labels(tmp_path / "labels", rec.frames, labels, lmo_dir / "models")
    scene = BopScene(folder)
    assert scene.image_ids == [f.im_id for f in rec.frames[:3]] and scene.gt_info is not None
    back = [Label.from_json(d) for d in json.loads((folder / "labels.json").read_text())]
    assert all(np.allclose(a.R, b.R) and np.allclose(a.t, b.t) and a.source == b.source for a, b in zip(labels, back, strict=True))
    objects = [o for o in lmo_objects() if o.obj_id in OBJECTS]
    crops = LabelledCrops([folder], objects, 64, lmo_dir / "models", PhotometricConfig(prob=1.0), min_visib=0.1)
    item = crops[0]
    assert set(KEYS) <= set(item) and item["crop"].dtype == torch.uint8 and item["points"].shape == (3, 64, 64)
    mask = item["mask_visib"][0].numpy() > 0
    assert 0.05 < mask.mean() < 0.9 and np.abs(item["points"].numpy()[:, ~mask]).max() == 0
    assert np.abs(item["points"].numpy()[:, mask]).max() <= 1.0 + 1e-4  # surface points within the object's radius
    crops.epoch = 3
    assert torch.equal(crops[1]["crop"], crops[1]["crop"])  # a sample is a function of (seed, epoch, index)
    stream = CropStream(StreamConfig(objects=OBJECTS, size=64), lmo_dir / "models")
    a = next(mixed_batches(crops, stream, 4, 2, step=5, seed=0))
    b = next(mixed_batches(crops, stream, 4, 2, step=5, seed=0))
    assert all(torch.equal(a[k], b[k]) for k in KEYS) and a["crop"].shape[0] == 4  # a resumed step draws the same batch


def test_a_prediction_becomes_a_label_only_where_the_contour_agrees(recording, lmo_dir):
    rec = read_recording(recording)
    est = Estimator.load(SHIPPED_ESTIMATOR)
    geometry = object_geometry(est)
    frame = rec.frames[0]
    truth = {g.obj_id: g for g in BopScene(recording).gt[frame.im_id]}
    g = truth[6]
    turned, moved = cv2.Rodrigues(np.radians([8.0, -4.0, 4.0]))[0] @ g.R, g.t * 1.03 + np.array([0.004, -0.003, 0.0])
    near = Prediction(frame.im_id, g.obj_id, turned, moved, None)
    empty = Prediction(frame.im_id, g.obj_id, g.R, g.t + np.array([0.3, 0.2, 0.0]), None)  # where nothing is
    refiner = ContourRefiner(RefineConfig(), est.meshes)
    labels = label_frame(refiner, frame.rgb(), frame.K, [near, empty], [], geometry, ConsistencyConfig(), FillConfig())
    assert len(labels) == 1 and labels[0].source == "filled"
    points = est.meshes[g.obj_id][0]
    assert proj(labels[0].R, labels[0].t, g.R, g.t, frame.K, points) < 0.5 * proj(turned, moved, g.R, g.t, frame.K, points)


def _small(rounds: int = 1, steps: int = 2, localiser: bool = True) -> AdaptConfig:
    optim = OptimConfig(steps=steps, batch=4, lr=1e-4, warmup=1, workers=0, save_every=1000, val_every=1000)
    train = AdaptTrainConfig(optim=optim, real_per_batch=2, val_samples=2)
    frames = RenderedFrames(desk_scenes=0, plain_scenes=1, images_per_scene=2)
    tuned = AdaptLocaliserConfig(optim=dataclasses.replace(optim, batch=2, steps=steps if localiser else 0), val_frames=1, frames=frames)
    search = SearchConfig(views=3, places=1, step=0.15, margin=0.0, min_support=3)
    return AdaptConfig(rounds=rounds, pose=PoseSettings(threshold=0.3), search=search, train=train, localiser=tuned)


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return Estimator.load(path).agm.denoiser.state_dict()


@pytest.mark.slow
def test_a_round_runs_end_to_end_and_resumes_to_the_same_weights(recording, tmp_path, lmo_dir):
    rec = read_recording(recording)
    whole = Adaptation(rec, SHIPPED_ESTIMATOR, lmo_dir / "models", tmp_path / "whole", _small(steps=3), RunOptions(device="cpu"))
    final = whole.run(progress=False)
    assert final == tmp_path / "whole" / ADAPTED and final.is_file()
    report = json.loads((tmp_path / "whole" / "report.json").read_text())
    counts = report["rounds"][0]["counts"]
    assert counts["frames"] == 4 and counts["total"]["labels"] > 0 and (tmp_path / "whole" / "round0" / "contact_sheet.png").is_file()
    searched = {name for name, c in counts["objects"].items() if "searched" in c}  # those the scene predicts nowhere
    assert searched == {name for name, c in counts["objects"].items() if c["checked"] + c["filled"] + c["unfilled"] == 0}
    assert {"driller", "glue"} <= searched and (tmp_path / "whole" / "round0" / "search.json").is_file()
    adapted = Estimator.load(final)
    assert adapted.config.training["adapt"]["steps"] == 3 and adapted.localiser is not None and adapted.config.verifier is not None
    # The checkpoint is the fine-tune's EMA blended with the source's weights, not the EMA itself.
    ema = torch.load(state_path(tmp_path / "whole" / "round0" / AGM), weights_only=False)["ema"]
    tuned = {k.removeprefix("denoiser."): v for k, v in ema.items() if k.startswith("denoiser.")}
    source, written = _weights(SHIPPED_ESTIMATOR), _weights(final)
    expected = blend(source, tuned, AdaptTrainConfig().blend)
    assert all(torch.allclose(written[k], expected[k], rtol=0, atol=1e-7) for k in written)
    assert any(not torch.equal(written[k], tuned[k]) for k in written if written[k].is_floating_point())
    # ... and its localiser the localiser's fine-tune on the labelled frames and the rendered ones.
    rendered = list((tmp_path / "whole" / "frames" / "plain").glob("*/rgb/*"))
    assert adapted.config.training["adapt_localiser"]["steps"] == 3 and len(rendered) == 2
    shipped = Estimator.load(SHIPPED_ESTIMATOR).localiser.state_dict()
    assert any(not torch.allclose(v, shipped[k]) for k, v in adapted.localiser.state_dict().items() if v.is_floating_point())
    # interrupted and resumed (the AGM's stage: the localiser's resumes by the same loop)
    stopped = Adaptation(rec, SHIPPED_ESTIMATOR, lmo_dir / "models", tmp_path / "cut", _small(steps=3, localiser=False),
                         RunOptions(device="cpu", stop_at=1))  # fmt: skip
    (tmp_path / "cut" / "round0").mkdir()
    lines = (tmp_path / "whole" / "round0" / "candidates.jsonl").read_text().splitlines()
    (tmp_path / "cut" / "round0" / "candidates.jsonl").write_text("\n".join(lines[:-1]) + "\n")  # killed before the last frame
    assert stopped.run(progress=False) is None and not (tmp_path / "cut" / ADAPTED).exists()
    with pytest.raises(AdaptError, match="--resume"):
        Adaptation(rec, SHIPPED_ESTIMATOR, lmo_dir / "models", tmp_path / "cut", _small(steps=3, localiser=False))
    resumed = Adaptation(rec, SHIPPED_ESTIMATOR, lmo_dir / "models", tmp_path / "cut", _small(steps=3, localiser=False),
                         RunOptions(device="cpu"), resume=True)  # fmt: skip
    a, b = _weights(final), _weights(resumed.run(progress=False))
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(AdaptError, match="another config"):
        Adaptation(rec, SHIPPED_ESTIMATOR, lmo_dir / "models", tmp_path / "cut", _small(steps=5, localiser=False), resume=True)
    # A finished run resumed with more rounds goes on from its last: round 1 poses and trains from round 0's model.
    more = Adaptation(rec, SHIPPED_ESTIMATOR, lmo_dir / "models", tmp_path / "whole", _small(rounds=2, steps=3),
                      RunOptions(device="cpu"), resume=True)  # fmt: skip
    assert more.estimator_of(1) == tmp_path / "whole" / "round0" / ADAPTED
    two = _weights(more.run(progress=False))
    rounds = json.loads((tmp_path / "whole" / "report.json").read_text())["rounds"]
    assert len(rounds) == 2 and rounds[1]["labels"] > 0 and ("stopped" in rounds[1]) != bool(rounds[1].get("trained"))
    last = tmp_path / "whole" / ("round1" if rounds[1].get("trained") else "round0") / ADAPTED
    last_weights = _weights(last)
    assert all(torch.equal(two[k], last_weights[k]) for k in two)


def test_a_blend_lies_between_the_source_and_the_fine_tune():
    torch.manual_seed(0)
    source = {"w": torch.randn(4, 3), "b": torch.randn(3).to(torch.bfloat16), "count": torch.tensor(7)}
    tuned = {"w": torch.randn(4, 3), "b": torch.randn(3).to(torch.bfloat16), "count": torch.tensor(9)}
    assert all(torch.equal(blend(source, tuned, 1.0)[k], tuned[k]) for k in tuned)
    assert torch.equal(blend(source, tuned, 0.0)["w"], source["w"]) and blend(source, tuned, 0.0)["count"] == 9
    mid = blend(source, tuned, 0.7)
    assert torch.allclose(mid["w"], 0.3 * source["w"] + 0.7 * tuned["w"], atol=1e-6) and mid["b"].dtype == torch.bfloat16
    with pytest.raises(ValueError, match="differ"):
        blend(source, {"w": tuned["w"]}, 0.5)
    with pytest.raises(ValueError, match="blend"):
        AdaptTrainConfig(blend=1.5)


def test_a_config_changes_only_the_values_it_names(tmp_path):
    request = AdaptRequest(tmp_path, tmp_path / "out", SHIPPED_ESTIMATOR, tmp_path, config="{train: {optim: {lr: 3.0e-5}}, rounds: 1}")
    cfg = adapt_config(request)
    default = AdaptTrainConfig().optim
    assert cfg.rounds == 1 and cfg.train.optim.lr == 3.0e-5
    assert dataclasses.replace(cfg.train.optim, lr=default.lr) == default
    assert adapt_config(dataclasses.replace(request, steps=300)).train.optim.steps == 300
    search = adapt_config(dataclasses.replace(request, config="{search: {views: 0, levels: [0.0, 0.02]}}")).search
    assert search == SearchConfig(views=0, levels=(0.0, 0.02))


def test_bad_input_is_one_line_and_exit_2(recording, tmp_path, lmo_dir, capsys):
    def refused(**changes) -> str:
        request = AdaptRequest(recording, tmp_path / "out", SHIPPED_ESTIMATOR, lmo_dir / "models", progress=False)
        request = dataclasses.replace(request, **changes)
        assert run_adapt(request) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("axispose adapt: ")
        return err

    assert "no such folder" in refused(recording=tmp_path / "nowhere")
    assert "no models folder" in refused(models=tmp_path / "nowhere")
    assert "nowhere.safetensors" in refused(checkpoint=tmp_path / "nowhere.safetensors")
    assert "rounds" in refused(config="{rounds: 0}")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "something").write_text("x")
    assert "not an adaptation" in refused(out=tmp_path / "taken")
    assert "nothing to resume" in refused(out=tmp_path / "fresh", resume=True)
    blank = tmp_path / "blank"
    (blank / "rgb").mkdir(parents=True)
    cams = json.loads((recording / "scene_camera.json").read_text())
    (blank / "scene_camera.json").write_text(json.dumps(cams))
    for k in cams:
        cv2.imwrite(str(blank / "rgb" / f"{int(k):06d}.png"), np.full((480, 640, 3), 90, np.uint8))
    assert "no labels" in refused(recording=blank, out=tmp_path / "blank_out", config="{rounds: 1}")


def test_recoloured_models_keep_their_geometry_and_wear_other_colours(lmo_dir, tmp_path):
    from axispose_core.data.bop_models import model_path
    from axispose_core.data.meshes import load_ply
    from axispose_core.data.recolour import recoloured_models

    out = recoloured_models(lmo_dir / "models", tmp_path / "a", seed=3)
    again = recoloured_models(lmo_dir / "models", tmp_path / "b", seed=3)
    for obj_id in (1, 10):
        mesh, new = load_ply(model_path(lmo_dir / "models", obj_id)), load_ply(model_path(out, obj_id))
        np.testing.assert_allclose(new.vertices, mesh.vertices, atol=1e-4)
        assert (new.faces == mesh.faces).all()
        hue = [cv2.cvtColor(m.colors.reshape(-1, 1, 3), cv2.COLOR_RGB2HSV)[:, 0, 0].astype(int) for m in (mesh, new)]
        turned = np.minimum(abs(hue[1] - hue[0]), 180 - abs(hue[1] - hue[0]))
        assert np.median(turned[mesh.colors.std(axis=1) > 8]) > 30  # coloured vertices turned in hue (OpenCV's 0-180)
        assert (load_ply(model_path(again, obj_id)).colors == new.colors).all()  # one seed, one look
