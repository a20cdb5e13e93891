"""Training plumbing: a short run writes a loadable estimator, resumes exactly, and runs under torchrun (gloo)."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml
from conftest import REPO, TINY_AGM_YAML

from axispose_core.cli import main
from axispose_core.data.synth.config import SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.estimator import Estimator

OPTIM = {"steps": 4, "batch": 2, "workers": 0, "warmup": 1, "save_every": 2, "val_every": 2}
TINY = {
    "optim": OPTIM,
    "val_samples": 2,
    "val_steps": 1,
    "agm": TINY_AGM_YAML,
}


@pytest.fixture(scope="module")
def data(tmp_path_factory, lmo_dir):
    out = tmp_path_factory.mktemp("traindata")
    generate(SynthConfig(seed=9, scenes=1, images_per_scene=3, objects=(1, 5, 6)), lmo_dir / "models", out, progress=False)
    return out


def _config(tmp_path, **overrides):
    """A tiny TrainConfig YAML; overrides of optimisation fields (steps, lr, ...) go into its `optim` section."""
    path = tmp_path / f"cfg_{len(list(tmp_path.glob('cfg_*.yaml')))}.yaml"
    optim = OPTIM | {k: v for k, v in overrides.items() if k in OPTIM or k in ("lr", "bf16", "seed")}
    path.write_text(yaml.safe_dump({**TINY, **{k: v for k, v in overrides.items() if k not in optim}, "optim": optim}))
    return str(path)


def test_more_objects_than_the_config_has_rows_need_no_edit(data, tmp_path):
    """The data shows 3 objects, the config's encoder embeds 2: the run gives the embedding a row for each."""
    tiny = {**TINY_AGM_YAML, "denoiser": {**TINY_AGM_YAML["denoiser"], "encoder": {**TINY_AGM_YAML["denoiser"]["encoder"], "objects": 2}}}
    cfg = _config(tmp_path, steps=1, agm=tiny)
    out = tmp_path / "three.safetensors"
    assert main(["train", "--data", str(data), "--out", str(out), "--config", cfg, "--threads", "1"]) == 0
    est = Estimator.load(out)
    assert len(est.config.objects) == 3 and est.config.agm.denoiser.encoder.objects == 3


@pytest.mark.slow
def test_short_run_then_resume(data, tmp_path):
    out = tmp_path / "agm.safetensors"
    cfg = _config(tmp_path)
    assert main(["train", "--data", str(data), "--val", str(data), "--out", str(out), "--config", cfg, "--threads", "1"]) == 0
    state_file = str(out) + ".state.pt"
    resume = ["--resume", state_file]
    est = Estimator.load(out)
    assert est.config.training["steps"] == 4 and {o.obj_id for o in est.config.objects} == {1, 5, 6}
    state = torch.load(state_file, weights_only=False)
    assert state["step"] == 4
    rows = (tmp_path / "agm.csv").read_text().splitlines()
    assert rows[0].startswith("step,samples,loss") and any(r.split(",")[5] for r in rows[1:])  # validation logged
    # Another recipe is refused; the same config continues from step 4 (already done).
    with pytest.raises(ValueError, match=r"another configuration \(optim\)"):
        main(["train", "--data", str(data), "--out", str(out), "--config", _config(tmp_path, lr=5e-4), *resume])
    assert main(["train", "--data", str(data), "--out", str(out), "--config", cfg, *resume]) == 0
    assert torch.load(state_file, weights_only=False)["step"] == 4
    # More steps extend the run; its training time carries over the calls (as if the first had trained 1,000 s).
    state = torch.load(state_file, weights_only=False)
    assert 0 < state["seconds"] < 1000
    torch.save({**state, "seconds": 1000.0}, state_file)
    longer = _config(tmp_path, steps=6)
    assert main(["train", "--data", str(data), "--val", str(data), "--out", str(out), "--config", longer, *resume]) == 0
    state, training = torch.load(state_file, weights_only=False), Estimator.load(out).config.training
    assert state["step"] == 6 and training["steps"] == 6
    assert 1000 < training["seconds"] == state["seconds"] < 1000 + 600
    resumed = [float(r.split(",")[4]) for r in (tmp_path / "agm.csv").read_text().splitlines()[1:] if int(r.split(",")[0]) > 4]
    assert resumed and all(1000 < t < 1600 for t in resumed)  # the CSV's clock goes on from the saved time


@pytest.mark.slow
def test_torchrun_two_cpu_processes_with_gloo(data, tmp_path):
    out = tmp_path / "ddp.safetensors"
    torchrun = os.path.join(os.path.dirname(sys.executable), "torchrun")
    cmd = [torchrun, "--standalone", "--nproc_per_node", "2", "-m", "axispose_core.cli", "train", "--data", str(data),
           "--out", str(out), "--config", _config(tmp_path, steps=2), "--device", "cpu", "--threads", "1"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert Estimator.load(out).config.training["steps"] == 2


def test_init_starts_from_a_checkpoints_weights(data, tmp_path):
    first = tmp_path / "first.safetensors"
    assert main(["train", "--data", str(data), "--out", str(first), "--config", _config(tmp_path), "--threads", "1"]) == 0
    trained = Estimator.load(first).agm.denoiser.state_dict()
    # zero steps from the checkpoint: the new run's weights are exactly the ones it started from
    again = tmp_path / "again.safetensors"
    assert main(["train", "--data", str(data), "--out", str(again), "--config", _config(tmp_path, steps=0), "--init", str(first)]) == 0
    started = Estimator.load(again)
    assert started.config.training["init"] == str(first)
    assert all(torch.equal(v, trained[k]) for k, v in started.agm.denoiser.state_dict().items())
    # a later call of the warm-started run resumes its own state and still names where the run began
    state = str(again) + ".state.pt"
    assert main(["train", "--data", str(data), "--out", str(again), "--config", _config(tmp_path, steps=1), "--resume", state]) == 0
    assert Estimator.load(again).config.training["init"] == str(first)
    assert Estimator.load(again).config.training["steps"] == 1
    fresh = tmp_path / "fresh.safetensors"
    assert main(["train", "--data", str(data), "--out", str(fresh), "--config", _config(tmp_path, steps=0)]) == 0
    assert not all(torch.equal(v, trained[k]) for k, v in Estimator.load(fresh).agm.denoiser.state_dict().items())
    # another network is refused, naming both
    wider = {**TINY["agm"], "denoiser": {**TINY["agm"]["denoiser"], "channels": 16}}
    with pytest.raises(ValueError, match="blocks per stage and the objects may grow"):
        main(["train", "--data", str(data), "--out", str(tmp_path / "w.safetensors"), "--config", _config(tmp_path, agm=wider),
              "--init", str(first)])  # fmt: skip


@pytest.mark.slow
def test_stream_training_is_seeded_resumable_and_validated(lmo_dir, tmp_path):
    """On the crop stream (no BOP folders): two runs of one config give the same weights; the CSV logs the crops
    seen and held-out metrics; a resumed run continues."""
    cfg = _config(tmp_path, steps=3, val_every=3, stream={"objects": [1, 5]})
    runs = []
    for name in ("a", "b"):
        out = tmp_path / f"{name}.safetensors"
        assert main(["train", "--models", str(lmo_dir / "models"), "--out", str(out), "--config", cfg, "--threads", "1"]) == 0
        runs.append(Estimator.load(out))
    a, b = (r.agm.denoiser.state_dict() for r in runs)
    assert all(torch.equal(v, b[k]) for k, v in a.items())
    assert {o.obj_id for o in runs[0].config.objects} == {1, 5} and "crop stream" in runs[0].config.training["data"][0]
    header, *rows = (tmp_path / "a.csv").read_text().splitlines()
    columns = header.split(",")
    assert columns[:6] == ["step", "samples", "loss", "lr", "seconds", "val_loss"]
    last = dict(zip(columns, rows[-1].split(","), strict=True))
    assert last["step"] == "3" and last["samples"] == "6"  # 3 steps of batch 2
    # held-out metrics of every part measured: keypoints, both depth sources' errors, the surface points
    assert float(last["val_kp_err_px"]) > 0 and float(last["val_depth_head"]) > 0 and float(last["val_points_err"]) > 0
    state = str(tmp_path / "a.safetensors") + ".state.pt"
    longer = _config(tmp_path, steps=5, val_every=3, stream={"objects": [1, 5]})
    assert main(["train", "--models", str(lmo_dir / "models"), "--out", str(tmp_path / "a.safetensors"), "--config", longer,
                 "--resume", state]) == 0  # fmt: skip
    assert torch.load(state, weights_only=False)["step"] == 5
    with pytest.raises(ValueError, match="crop stream renders 32px"):
        main(["train", "--models", str(lmo_dir / "models"), "--out", str(tmp_path / "c.safetensors"),
              "--config", _config(tmp_path, stream={"size": 32})])  # fmt: skip


@pytest.mark.slow
def test_loss_falls_on_the_stream(lmo_dir):
    """A small AGM trained for 40 steps on fresh stream crops lowers its loss on a fixed held-out batch."""
    from dataclasses import replace

    from conftest import TINY_AGM

    from axispose_core.agm.model import AxisGenerator
    from axispose_core.data.synth.config import StreamConfig
    from axispose_core.data.synth.stream import CropStream, CropStreamDataset, stream_loader
    from axispose_core.train.losses import AGMObjective

    torch.manual_seed(0)
    model = AGMObjective(AxisGenerator(replace(TINY_AGM, train_guidance=False)))
    stream = CropStream(StreamConfig(objects=(1,), seed=3), lmo_dir / "models")
    held = [CropStreamDataset(CropStream(StreamConfig(objects=(1,), seed=4), lmo_dir / "models"))[i] for i in range(8)]
    batch = {k: torch.stack([h[k] for h in held]) for k in ("crop", "axes", "object", "points", "mask_visib")}

    def held_out_loss() -> float:
        with torch.no_grad():
            return float(np.mean([model(batch, torch.Generator().manual_seed(k)).item() for k in range(4)]))

    before = held_out_loss()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for fresh in stream_loader(stream, 8, stop=8 * 40):
        opt.zero_grad()
        model(fresh).backward()
        opt.step()
    assert held_out_loss() < 0.8 * before


def test_a_curriculum_trains_on_each_stage_in_turn_and_resumes_inside_it(lmo_dir):
    """Stage (until=2, unoccluded) gives steps 0 and 1, the run's stream the rest, each stage's samples at the
    indices of their steps; starting at step 1 (a resumed run) gives the same batches from there."""
    from axispose_core.data.synth.config import StreamConfig
    from axispose_core.data.synth.stream import CropStream, CropStreamDataset
    from axispose_core.train.agm import CurriculumStage, curriculum_batches

    hard = StreamConfig(objects=(1, 5), seed=3, visib=(0.2, 0.6))
    easy = CurriculumStage(until=2, visib=(0.7, 1.0)).stream(hard)
    stages = [(2, CropStream(easy, lmo_dir / "models")), (None, CropStream(hard, lmo_dir / "models"))]
    batches = []
    for b in curriculum_batches(stages, 2, 0):
        batches.append(b)
        if len(batches) == 4:
            break
    assert all(float(v) >= 0.7 for b in batches[:2] for v in b["visib"])  # unoccluded (the frame's edge may cut some)
    assert all(0.2 <= float(v) <= 0.6 for b in batches[2:] for v in b["visib"])  # the run's stream
    expected = CropStreamDataset(stages[1][1])[5]  # step 2, second sample: index 2 * 2 + 1
    assert torch.equal(batches[2]["crop"][1], expected["crop"])
    resumed = next(iter(curriculum_batches(stages, 2, 1)))
    assert torch.equal(resumed["crop"], batches[1]["crop"])


def test_a_state_saved_before_a_field_existed_resumes_if_the_field_is_left_at_its_default(tmp_path):
    from dataclasses import replace

    from conftest import TINY_AGM

    from axispose_core.agm.model import AxisGenerator
    from axispose_core.train.agm import CurriculumStage, TrainConfig
    from axispose_core.train.resume import RunParts, load_run_state, save_run_state

    cfg = TrainConfig(agm=TINY_AGM)
    model = AxisGenerator(TINY_AGM)
    opt = torch.optim.AdamW(model.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    path = tmp_path / "state.pt"
    parts = RunParts(model, model, opt, sched)
    save_run_state(path, cfg, parts, 7)
    state = torch.load(path, weights_only=False)
    del state["config"]["curriculum"]  # as written before the field was added
    torch.save(state, path)
    assert load_run_state(path, cfg, parts)[0] == 7
    with pytest.raises(ValueError, match="curriculum"):
        load_run_state(path, replace(cfg, curriculum=(CurriculumStage(until=5),)), parts)


def test_a_resumed_run_may_change_its_stream_from_the_saved_step_on_but_not_before(tmp_path):
    from dataclasses import replace

    from conftest import TINY_AGM

    from axispose_core.agm.model import AxisGenerator
    from axispose_core.data.synth.config import StreamConfig
    from axispose_core.train.agm import CurriculumStage, TrainConfig, same_stream_before
    from axispose_core.train.resume import RunParts, load_run_state, save_run_state

    easy = TrainConfig(agm=TINY_AGM, stream=StreamConfig(occluded_prob=0.0, clutter_prob=0.0, neighbours=(0, 0)))
    model = AxisGenerator(TINY_AGM)
    opt = torch.optim.AdamW(model.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    path = tmp_path / "state.pt"
    parts = RunParts(model, model, opt, sched)
    save_run_state(path, easy, parts, 7)

    def resume(cfg: TrainConfig) -> int:
        return load_run_state(path, cfg, parts, ("stream", "curriculum"), lambda s, n: same_stream_before(s, cfg, n))[0]

    occluded = replace(easy, stream=StreamConfig(occluded_prob=0.4))
    assert resume(replace(occluded, curriculum=(CurriculumStage(until=7),))) == 7  # the easy stream up to step 7, then occluded
    assert resume(replace(occluded, curriculum=(CurriculumStage(until=9),))) == 7  # a stage may also end later
    with pytest.raises(ValueError, match="stream"):
        resume(replace(occluded, curriculum=(CurriculumStage(until=5),)))  # steps 5 and 6 were trained on the easy stream
    with pytest.raises(ValueError, match="curriculum"):
        resume(replace(easy, curriculum=(CurriculumStage(until=3, occluded_prob=0.5),)))
    with pytest.raises(ValueError, match="min_visib"):
        resume(replace(occluded, min_visib=0.5, curriculum=(CurriculumStage(until=7),)))


def test_a_training_kit_trains_from_its_own_folder_and_returns_the_checkpoint_in_parts(lmo_dir, tmp_path):
    """tools/train_kit.py packs what a bare machine lacks; its run.sh trains with the kit's models and leaves a
    checkpoint that joins back from its parts, with the run's CSV and log beside them."""
    kit, out = tmp_path / "kit", tmp_path / "back"
    subprocess.run([sys.executable, str(REPO / "tools" / "train_kit.py"), "--out", str(kit), "--models", str(lmo_dir / "models_eval"),
                    "--lite0-stages", "1"], cwd=REPO, check=True, capture_output=True)  # fmt: skip
    weights = torch.load(next((kit / "site").glob("*/models/*.pth")), weights_only=True)
    assert weights and all(k.startswith(("_conv_stem", "_bn0", "_blocks.0.")) for k in weights)  # stage 0 only
    assert (kit / "photos" / "skimage" / "data" / "astronaut.png").is_file() and (kit / "models" / "models_info.json").is_file()
    cfg = _config(tmp_path, steps=2, val_every=2, stream={"objects": [1]})
    done = subprocess.run(["bash", str(kit / "run.sh"), str(out), "tiny", "--config", cfg, "--threads", "1", "--device", "cpu"],
                          cwd=REPO, env={**os.environ, "PYTHON": sys.executable}, capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr + (out / "tiny.log").read_text()
    joined = tmp_path / "tiny.safetensors"
    joined.write_bytes(b"".join(p.read_bytes() for p in sorted(out.glob("tiny.part*"))))
    assert [o.obj_id for o in Estimator.load(joined).config.objects] == [1]
    assert (out / "tiny.csv").read_text().splitlines()[-1].startswith("2,")
    failed = subprocess.run(["bash", str(kit / "run.sh"), str(out), "bad", "--config", str(tmp_path / "missing.yaml")],
                            cwd=REPO, env={**os.environ, "PYTHON": sys.executable}, capture_output=True, text=True)  # fmt: skip
    assert failed.returncode != 0 and not list(out.glob("bad.part*"))


def test_held_out_rotation_errors_are_taken_up_to_symmetry(lmo_dir, monkeypatch):
    """The trainer's validation takes an eggbox read as its half turn about z as no error (eval's definition); an ape
    read so stays 180° off, and without the symmetries the eggbox does too."""
    from conftest import TINY_AGM

    from axispose_core.agm.model import AxisGenerator
    from axispose_core.data.synth.config import StreamConfig
    from axispose_core.tbm.backproject import Backprojection
    from axispose_core.tbm.reader import SHIPPED_READER, load_reader
    from axispose_core.train import agm as trainer
    from axispose_core.train.dataset import AxisCropDataset
    from axispose_core.train.sources import CropSources

    sources = CropSources(models=lmo_dir / "models")
    stream = StreamConfig(objects=(1, 10), seed=4)
    objects, _, _ = sources.training(AxisCropDataset, stream, 64, 0.1, 0)
    symmetries = sources.symmetries(objects)
    assert set(symmetries) == {10} and len(symmetries[10]) == 2  # the eggbox: identity and a half turn about z
    items = sources.held_out(AxisCropDataset, objects, stream, 7, 64, 8, 0)
    scales = torch.tensor([o.scale for o in objects], dtype=torch.float64)
    batch = trainer.with_depth_target(trainer._batch_of(items), scales, 64)
    ids = [objects[int(it["object"])].obj_id for it in items]
    assert 0 < ids.count(10) < len(ids)
    half_turn = np.diag([-1.0, -1.0, 1.0])
    turned = [Backprojection(R @ half_turn, t, True) for R, t in zip(batch["R"].numpy(), batch["t"].numpy(), strict=True)]
    monkeypatch.setattr(trainer, "backproject_readings", lambda *_: turned)
    agm, reader = AxisGenerator(TINY_AGM), load_reader(SHIPPED_READER)
    lengths = np.stack([o.axes.lengths for o in (objects[int(it["object"])] for it in items)])
    syms = [symmetries.get(i, []) for i in ids]
    assert trainer.validate(agm, reader, batch, lengths, 1, syms)["val_rot_within_15deg"] == ids.count(10) / len(ids)
    assert trainer.validate(agm, reader, batch, lengths, 1)["val_rot_within_15deg"] == 0.0
