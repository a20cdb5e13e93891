"""`axispose train --recipe`: a short recipe of every trainer runs end to end, resumes where a call stopped, rebuilds
nothing that is done, refuses a stage changed after it was built, and records the recipe in the checkpoint."""

import dataclasses
import json
from pathlib import Path

import pytest
import torch
import yaml
from conftest import TINY_AGM_YAML, save_tiny_estimator

from axispose_core.cli import main
from axispose_core.estimator import Estimator
from axispose_core.tbm.reader import SHIPPED_READER
from axispose_core.train.loop import RunOptions
from axispose_core.train.reader import train_reader
from axispose_core.train.recipe import RecipeError, load_recipe
from axispose_core.train.recipe_runner import RecipeRunner

OPTIM = {"steps": 2, "batch": 2, "warmup": 1, "workers": 0, "save_every": 1, "val_every": 2}
SHIPPED_RECIPE = Path(__file__).resolve().parents[1] / "config" / "recipes" / "axispose_lmo.yaml"


def _recipe(models: Path) -> dict:
    return {
        "models": str(models),
        "data": {"frames": {"scenes": 1, "images_per_scene": 2, "seed": 3, "objects": [1, 5]}},
        "stages": [
            {"name": "reader", "trainer": "reader",
             "config": {"reader": {"channels": 8, "blocks": [1, 1, 1, 1, 1]}, "optim": dict(OPTIM), "val_samples": 4}},
            {"name": "agm", "trainer": "agm",
             "config": {"agm": TINY_AGM_YAML, "optim": dict(OPTIM), "val_samples": 2, "val_steps": 1, "stream": {"objects": [1, 5]}},
             "schedule": [{"steps": 6, "until": 2}, {"steps": 3}]},
            {"name": "agm_more", "trainer": "agm", "init": "agm", "changes": {"optim": {"seed": 1, "steps": 2}}},
            {"name": "unused", "trainer": "agm", "changes": {"optim": {"steps": 1}}},
            {"name": "localiser", "trainer": "localiser", "data": ["frames"],
             "config": {"localiser": {"input_size": [160, 128], "channels": [8, 16, 24, 32]}, "optim": dict(OPTIM), "val_frames": 2}},
        ],
        "estimator": {"agm": "agm_more", "reader": "reader", "localiser": "localiser", "config": {"ddim_steps": 2}},
    }  # fmt: skip


def _write(tmp_path: Path, recipe: dict, name: str = "tiny.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(recipe))
    return path


@pytest.mark.slow
def test_a_short_recipe_builds_resumes_and_records_itself(lmo_dir, tmp_path):
    path, out = _write(tmp_path, _recipe(lmo_dir / "models")), tmp_path / "run"
    recipe = load_recipe(path)
    assert [s.name for s in recipe.needed()] == ["reader", "agm", "agm_more", "localiser"]  # not "unused"
    assert recipe.stage("agm_more").config["optim"] == {**OPTIM, "seed": 1}  # the stage before, changed
    # A call whose time is up trains nothing; a stage stopped part-way (here after 1 of its 2 steps) goes on from
    # its resume state: its log has one header, not a restart's second.
    assert RecipeRunner(recipe, out, RunOptions(max_minutes=1e-6, progress=False)).run_all() is None
    assert not list(out.glob("*.safetensors"))
    reader = recipe.stage("reader")
    train_reader(reader.segment_config(reader.schedule[0]), out / "reader.safetensors", RunOptions(stop_at=1, progress=False))
    assert main(["train", "--recipe", str(path), "--out", str(out), "--threads", "1"]) == 0
    assert (out / "reader.csv").read_text().count("step,") == 1
    done = {s: json.loads((out / f"{s}.done.json").read_text()) for s in ("reader", "agm", "agm_more", "localiser")}
    assert done["reader"]["steps"] == 2 and done["agm"]["steps"] == 3 and done["agm_more"]["init"] == str(out / "agm.safetensors")
    assert not (out / "unused.safetensors").exists()
    est = Estimator.load(out / "tiny.safetensors")
    assert est.config.ddim_steps == 2 and est.localiser is not None and {o.obj_id for o in est.config.objects} == {1, 5}
    training = est.config.training
    assert training["recipe_sha256"] == recipe.sha256 and training["recipe"]["stages"][1]["schedule"][0] == {"steps": 6, "until": 2}
    assert [s["name"] for s in training["stages"]] == ["reader", "agm", "agm_more", "localiser"]
    # Done stages are not trained again.
    mtimes = {p.name: p.stat().st_mtime_ns for p in out.glob("*.safetensors") if p.name != "tiny.safetensors"}
    assert main(["train", "--recipe", str(path), "--out", str(out), "--threads", "1"]) == 0
    assert mtimes == {p.name: p.stat().st_mtime_ns for p in out.glob("*.safetensors") if p.name != "tiny.safetensors"}
    # A stage changed after it was built is refused, not silently mixed with the old weights.
    changed = _recipe(lmo_dir / "models")
    changed["stages"][2]["changes"]["optim"]["seed"] = 2
    with pytest.raises(RecipeError, match=r"agm_more\.safetensors was built by another config"):
        RecipeRunner(load_recipe(_write(tmp_path, changed, "changed.yaml")), out, RunOptions(progress=False)).run_all()
    # Existing checkpoints may stand in for stages: nothing trains, and the record says which were adopted.
    adopted = {"reader": str(SHIPPED_READER), "agm_more": str(out / "agm_more.safetensors")}
    adopted["localiser"] = str(out / "localiser.safetensors")
    again = RecipeRunner(recipe, tmp_path / "adopted", RunOptions(progress=False), adopted).run_all()
    stages = Estimator.load(again).config.training["stages"]
    assert [s.get("adopted") for s in stages] == [adopted["reader"], adopted["agm_more"], adopted["localiser"]]
    assert not (tmp_path / "adopted" / "agm.safetensors").exists()
    # What an adopted stage started from, adopted too, joins the record: how the adopted weights were trained.
    chain = RecipeRunner(recipe, tmp_path / "chain", RunOptions(progress=False), {**adopted, "agm": str(out / "agm.safetensors")})
    stages_chain = Estimator.load(chain.run_all()).config.training["stages"]
    assert [(s["name"], s.get("adopted")) for s in stages_chain] == [
        ("reader", adopted["reader"]), ("agm", str(out / "agm.safetensors")), ("agm_more", adopted["agm_more"]),
        ("localiser", adopted["localiser"]),
    ]  # fmt: skip
    assert stages_chain[1]["training"]["steps"] == 3
    # Re-assembled from its own output, a stage keeps the record of the run that trained it: the record does not
    # nest itself once more with every re-assembly.
    records = [stages]
    for k in (1, 2):
        again = RecipeRunner(recipe, tmp_path / f"again{k}", RunOptions(progress=False), {**adopted, "agm_more": str(again)}).run_all()
        records.append(Estimator.load(again).config.training["stages"])
    assert records[1][1]["training"] == records[2][1]["training"] == stages[1]["training"]
    provenance = ("adopted", "file_sha256")  # which file stood in: a new one each time
    assert [{k: v for k, v in s.items() if k not in provenance} for s in records[1]] == [
        {k: v for k, v in s.items() if k not in provenance} for s in records[2]
    ]
    # An estimator that no recipe assembled records how its AGM was trained, not its localiser: a localiser adopted
    # from it has no record.
    plain = Estimator.load(again)
    plain = Estimator(dataclasses.replace(plain.config, training=stages[1]["training"]), plain.agm, plain.reader, "cpu", plain.localiser)
    plain.save(tmp_path / "plain.safetensors")
    from_plain = {**adopted, "localiser": str(tmp_path / "plain.safetensors")}
    assembled = RecipeRunner(recipe, tmp_path / "plain", RunOptions(progress=False), from_plain).run_all()
    stages_plain = Estimator.load(assembled).config.training["stages"]
    assert "training" not in stages_plain[2] and stages_plain[1]["training"] == stages[1]["training"]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r["stages"][0].update(colour="red"), "stage reader: unknown key"),
        (lambda r: r["stages"][2].update(init="nowhere"), "init 'nowhere' is not an earlier agm stage"),
        (lambda r: r["stages"][1]["config"]["optim"].update(stpes=3), "stpes"),
        (lambda r: r["stages"][4].update(data=["elsewhere"]), "data elsewhere not in the recipe's data"),
        (lambda r: r["stages"][1].update(schedule=[{"steps": 6}, {"steps": 3}]), "every segment but the last stops"),
        (lambda r: r["estimator"].update(localiser="agm"), "localiser must name a localiser stage"),
        (lambda r: r["estimator"]["config"].update(ddim_stpes=2), "ddim_stpes"),
        (lambda r: r["estimator"]["config"].update(refine={"line": 100}), "line"),
        (lambda r: r["data"]["frames"].update(randomization={"light": {"ambiant": [0.2, 1.0]}}), "ambiant"),
        (lambda r: r["data"]["frames"].update(scene={"lookalike": 0.5}), "lookalike"),
        (lambda r: r["estimator"].update(verifier={"data": ["elsewhere"]}), "verifier needs data from the recipe's data"),
        (lambda r: r["estimator"].update(verifier={"data": ["frames"], "min_scor": 0.2}), "min_scor"),
        (lambda r: r["estimator"].update(verifier={"data": ["frames"], "min_score": 1.5}), "min_score must lie in"),
        (lambda r: r["estimator"]["config"].update(verifier={"weights": [1, 0, 0, 0]}), "verifier"),  # fitted, not set
        (lambda r: r.update(adapt={"config": {}}), "adapt: needs recording"),
        (lambda r: r.update(adapt={"recording": "x", "config": {"rounds": 0}}), "rounds must be >= 1"),
        (lambda r: r.update(adapt={"recording": "x", "config": {"train": {"blnd": 0.5}}}), "blnd"),
    ],
)
def test_a_recipe_with_a_mistake_is_refused_before_training(lmo_dir, tmp_path, capsys, edit, message):
    recipe = _recipe(lmo_dir / "models")
    edit(recipe)
    path = _write(tmp_path, recipe)
    with pytest.raises(RecipeError, match=message):
        load_recipe(path)
    assert main(["train", "--recipe", str(path), "--out", str(tmp_path / "run")]) == 2  # one line, exit 2
    assert message.split("'")[0] in capsys.readouterr().err and not (tmp_path / "run").exists()


def test_the_verifier_is_fitted_on_the_assembled_checkpoint_and_an_adopted_one_is_not_kept(lmo_dir, tmp_path, monkeypatch):
    """Assembly fits the recipe's verifier on its data with the checkpoint as stored; an adopted file's verifier,
    fitted to other weights, does not carry over into a checkpoint whose recipe has none."""
    from axispose_core.localiser.model import Localiser, LocaliserConfig
    from axispose_core.localiser.verifier import DetectionVerifier
    from axispose_core.trunks import ResidualBNConfig

    old = DetectionVerifier((1.0, 0.0, 0.0, 0.0))
    tiny = Estimator.load(save_tiny_estimator(tmp_path / "tiny.safetensors"))
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32))))
    tiny.with_localiser(localiser).with_verifier(old).save(tmp_path / "verified.safetensors")
    verified = str(tmp_path / "verified.safetensors")
    adopt = {"reader": str(SHIPPED_READER), "agm_more": verified, "localiser": verified}
    calls = []

    def fake_fit(est, data, config, progress=False):
        calls.append((est.config.verifier, [Path(d).name for d in data], config.min_score))
        return DetectionVerifier((0.5, 1.0, 0.0, -1.0), config.min_score), {"hits": 3}

    monkeypatch.setattr("axispose_core.train.recipe_runner.fit_verifier", fake_fit)
    plain = RecipeRunner(load_recipe(_write(tmp_path, _recipe(lmo_dir / "models"))), tmp_path / "plain", RunOptions(progress=False), adopt)
    assert Estimator.load(plain.run_all()).config.verifier is None and calls == []
    recipe = _recipe(lmo_dir / "models")
    recipe["estimator"]["verifier"] = {"data": ["frames"], "min_score": 0.25}
    path = RecipeRunner(load_recipe(_write(tmp_path, recipe, "v.yaml")), tmp_path / "v", RunOptions(progress=False), adopt).run_all()
    est = Estimator.load(path)
    assert calls == [(None, ["frames"], 0.25)]  # fitted on the assembled checkpoint, not the adopted one's verifier
    assert est.config.verifier == DetectionVerifier((0.5, 1.0, 0.0, -1.0), 0.25) and est.config.training["verifier"] == {"hits": 3}
    assert est.config.training["recipe"]["estimator"]["verifier"] == {"data": ["frames"], "min_score": 0.25}


def test_the_estimators_refine_settings_attach_the_refiner_meshes(lmo_dir, tmp_path):
    """`estimator.config.refine` gives the checkpoint a contour refiner with those settings and the meshes of the
    recipe's models (its objects', from BOP's decimated models_eval beside them)."""
    from axispose_core.localiser.model import Localiser, LocaliserConfig
    from axispose_core.trunks import ResidualBNConfig

    tiny = Estimator.load(save_tiny_estimator(tmp_path / "tiny.safetensors"))
    localiser = Localiser(LocaliserConfig(obj_ids=(1, 5), input_size=(160, 128), trunk=ResidualBNConfig(widths=(8, 16, 24, 32))))
    tiny.with_localiser(localiser).save(tmp_path / "loc.safetensors")
    located = str(tmp_path / "loc.safetensors")
    adopt = {"reader": str(SHIPPED_READER), "agm_more": located, "localiser": located}
    recipe = _recipe(lmo_dir / "models")
    recipe["estimator"]["config"]["refine"] = {"lines": 100}
    est = Estimator.load(RecipeRunner(load_recipe(_write(tmp_path, recipe)), tmp_path / "run", RunOptions(progress=False), adopt).run_all())
    assert est.config.refine.lines == 100 and sorted(est.meshes) == [1, 5] and est.refiner is not None
    assert len(est.meshes[1][1]) == 5646  # the ape's models_eval mesh


def test_a_fresh_trunk_stage_starts_from_its_inits_denoiser_with_a_new_trunk(tmp_path):
    """`fresh_trunk: SEED` starts an AGM stage from its init's weights with the trunk anew: the start is written
    beside the stage, the same seed gives the same file, and the key is refused where it cannot apply."""
    recipe = _recipe(tmp_path)
    recipe["stages"].append({"name": "anew", "trainer": "agm", "init": "agm", "fresh_trunk": 4})
    loaded = load_recipe(_write(tmp_path, recipe))
    assert loaded.stage("anew").fresh_trunk == 4
    assert "fresh_trunk" not in loaded.as_dict()["stages"][1]  # the records of stages without it stay as they were
    out = tmp_path / "run"
    out.mkdir()
    save_tiny_estimator(out / "agm.safetensors")
    runner = RecipeRunner(loaded, out, RunOptions(progress=False))
    start = runner._init(loaded.stage("anew"))
    assert start == out / "anew.init.safetensors" and runner._init(loaded.stage("agm_more")) == out / "agm.safetensors"
    trained, first = Estimator.load(out / "agm.safetensors").agm.state_dict(), Estimator.load(start).agm.state_dict()
    trunk = [k for k in first if k.startswith("denoiser.encoder.trunk.") and first[k].ndim > 1]  # not the norms' ones
    assert trunk and all(not torch.equal(first[k], trained[k]) for k in trunk)
    assert torch.equal(first["denoiser.out.2.weight"], trained["denoiser.out.2.weight"])
    again = Estimator.load(runner._init(loaded.stage("anew"))).agm.state_dict()
    assert all(torch.equal(v, first[k]) for k, v in again.items())
    for stage in ({"name": "x", "trainer": "agm", "fresh_trunk": 4}, {"name": "x", "trainer": "agm", "init": "agm", "fresh_trunk": True}):
        bad = _recipe(tmp_path)
        bad["stages"].append(stage)
        with pytest.raises(RecipeError, match="fresh_trunk"):
            load_recipe(_write(tmp_path, bad, "bad.yaml"))


def test_the_shipped_recipe_resolves_and_is_the_shipped_models():
    """The recipe file describes the shipped checkpoint: the runner assembled it from this recipe (its hash), so
    a change to a stage's config must come with a model built by it."""
    recipe = load_recipe(SHIPPED_RECIPE)
    shipped = Path(__file__).resolve().parents[1] / "axispose_core" / "models" / "axispose_lmo.safetensors"
    assert Estimator.load(shipped).config.training["recipe_sha256"] == recipe.sha256
    needed = {s.name for s in recipe.needed()}
    assert {recipe.estimator[k] for k in ("agm", "reader", "localiser")} <= needed
    assert all(s.trainer != "agm" or s.config["agm"]["denoiser"]["size"] == 64 for s in recipe.stages)


def test_a_change_that_names_another_kind_replaces_the_slot(tmp_path):
    """A stage that puts another trunk under its network keeps none of the old trunk's fields (which the new
    trunk's config would refuse); a change of the same kind merges field by field."""
    recipe = _recipe(tmp_path)
    lite = {"kind": "efficientnet_lite0"}
    recipe["stages"] += [
        {"name": "b", "trainer": "agm", "init": "agm", "changes": {"agm": {"denoiser": {"encoder": {"trunk": lite}}}}},
        {"name": "c", "trainer": "agm", "changes": {"agm": {"denoiser": {"encoder": {"trunk": {**lite, "stages": 3}}}}}},
        {"name": "d", "trainer": "agm", "changes": {"agm": {"denoiser": {"encoder": {"trunk": {"weights": "none"}}}}}},
    ]  # fmt: skip
    stages = load_recipe(_write(tmp_path, recipe)).stages
    trunks = {s.name: s.config["agm"]["denoiser"]["encoder"]["trunk"] for s in stages if s.trainer == "agm"}
    assert trunks["agm"] == TINY_AGM_YAML["denoiser"]["encoder"]["trunk"] and "widths" in trunks["agm"]
    assert trunks["b"] == {"kind": "efficientnet_lite0"}
    assert trunks["d"] == {"kind": "efficientnet_lite0", "stages": 3, "weights": "none"}


def test_the_pretrained_variant_recipe_differs_from_the_shipped_one_in_its_trunks_only():
    """config/recipes/axispose_lmo_lite0.yaml (the networks on ImageNet-pretrained Lite0 trunks, kept to be
    compared with the shipped ones on real frames) resolves, and its AGM is the shipped recipe's but for the trunk."""
    variant, shipped = load_recipe(SHIPPED_RECIPE.with_name("axispose_lmo_lite0.yaml")), load_recipe(SHIPPED_RECIPE)

    def networks(recipe):
        stages = {s.name: s.config for s in recipe.stages}
        return stages[recipe.estimator["agm"]]["agm"], stages[recipe.estimator["localiser"]]["localiser"]

    (agm, localiser), (agm0, localiser0) = networks(variant), networks(shipped)
    for trunk in (agm["denoiser"]["encoder"].pop("trunk"), localiser["trunk"]):
        assert trunk["kind"] == "efficientnet_lite0" and trunk.get("weights", "imagenet") == "imagenet"
    assert agm0["denoiser"]["encoder"].pop("trunk")["kind"] == "residual_gn" and localiser0["trunk"]["kind"] == "residual_bn"
    assert agm == agm0
    # head_offaxis is measured on a trained network's depth head (bench/head_offaxis.py), so it is the shipped one's alone.
    assert variant.estimator["config"] == {k: v for k, v in shipped.estimator["config"].items() if k != "head_offaxis"}


def test_a_data_entry_changes_only_the_part_of_its_frame_recipes_scenes_and_look_it_names():
    from axispose_core.data.synth.config import recipe as synth_recipe
    from axispose_core.train.recipe import synth_config

    spec = {"scenes": 2, "seed": 5, "recipe": "desk", "randomization": {"light": {"ambient": [0.15, 1.0]}}}
    cfg = synth_config(spec)
    _, desk = synth_recipe("desk")
    assert cfg.randomization.light.ambient == (0.15, 1.0)
    assert cfg.randomization == dataclasses.replace(desk, light=dataclasses.replace(desk.light, ambient=(0.15, 1.0)))
    assert synth_config({"scenes": 2, "seed": 5, "recipe": "desk"}).randomization == desk
    scene, _ = synth_recipe("desk")
    alike = synth_config({**spec, "scene": {"lookalike_prob": 0.5}})
    assert alike.scene == dataclasses.replace(scene, lookalike_prob=0.5) and alike.randomization == cfg.randomization


@pytest.mark.slow
def test_a_recipe_that_adapts_writes_the_adapted_checkpoint_and_resumes(lmo_dir, tmp_path):
    """`adapt` adapts the assembled checkpoint on its recording (OUT/adapt): the checkpoint written is the adapted
    one and its record holds the recipe with the recording; a call stopped by the time cap writes none, the next goes
    on without assembling or training anew; an unreadable recording is one RecipeError."""
    from axispose_core.data.synth.config import CameraPathConfig, SynthConfig
    from axispose_core.data.synth.generate import generate
    from axispose_core.estimator import SHIPPED_ESTIMATOR

    generate(SynthConfig(seed=5, scenes=1, images_per_scene=4, objects=(1, 5, 6), camera_path=CameraPathConfig(orbit_deg=6.0)),
             lmo_dir / "models", tmp_path / "recording", progress=False)  # fmt: skip
    recipe = _recipe(lmo_dir / "models")
    recipe["estimator"]["config"]["refine"] = {}  # adaptation refines its labels on the checkpoint's meshes
    optim = {**OPTIM, "steps": 2, "batch": 4, "save_every": 1000, "val_every": 1000}
    recipe["adapt"] = {"recording": str(tmp_path / "recording" / "000000"),
                       "config": {"pose": {"threshold": 0.3}, "train": {"optim": optim, "real_per_batch": 2, "val_samples": 2},
                                  "localiser": {"optim": {"steps": 0}}, "search": {"views": 0}}}  # fmt: skip
    path = _write(tmp_path, recipe)
    adopt = {"reader": str(SHIPPED_READER), "agm_more": str(SHIPPED_ESTIMATOR), "localiser": str(SHIPPED_ESTIMATOR)}
    out = tmp_path / "run"
    assert RecipeRunner(load_recipe(path), out, RunOptions(max_minutes=1e-6, progress=False), adopt, name="tiny").run_all() is None
    assert not (out / "tiny.safetensors").exists()
    assembled = out / "tiny.assembled.safetensors"
    assert main(["train", "--recipe", str(path), "--out", str(out), "--threads", "1"]) == 0  # the adopted stages stay done
    final = out / "tiny.safetensors"
    adapted, source = Estimator.load(final), Estimator.load(assembled)
    assert adapted.config.training["adapt"]["steps"] == 2 and "adapt" not in source.config.training
    assert adapted.config.training["recipe"]["adapt"]["recording"] == recipe["adapt"]["recording"]
    weights, before = adapted.agm.denoiser.state_dict(), source.agm.denoiser.state_dict()
    assert any(not torch.equal(v, before[k]) for k, v in weights.items() if v.is_floating_point())
    made = {p: p.stat().st_mtime_ns for p in (assembled, out / "adapt" / "round0" / "agm.safetensors")}
    assert RecipeRunner(load_recipe(path), out, RunOptions(progress=False), adopt, name="tiny").run_all() == final
    assert made == {p: p.stat().st_mtime_ns for p in made}
    recipe["adapt"]["recording"] = str(tmp_path / "nowhere")
    with pytest.raises(RecipeError, match="adapt: "):
        RecipeRunner(load_recipe(_write(tmp_path, recipe, "gone.yaml")), tmp_path / "gone", RunOptions(progress=False), adopt).run_all()
