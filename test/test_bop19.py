"""BOP19 errors (MSSD, MSPD, VSD) against hand-computed cases, average recall's matching and counting, the results
file and the targets file, and `axispose eval`'s AR end to end."""

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.bop19 import FRACTIONS, BopImage, BopObject, average_recall, image_errors
from axispose_core.cli import main
from axispose_core.data.bop import BopFormatError, load_test_targets
from axispose_core.data.bop_models import load_models_info
from axispose_core.data.bop_results import BopEstimate, read_bop_results, write_bop_results
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.synth.config import SynthConfig
from axispose_core.data.synth.generate import generate
from axispose_core.evaluation.records import Prediction
from axispose_core.evaluation.run import EvalOptions, evaluate
from axispose_core.evaluation.summary import summarize
from axispose_core.metrics import mspd, mssd, symmetry_transformations, vsd
from axispose_core.objects import objects_from_models

CUBE = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)])
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
t0 = np.array([0.0, 0.0, 1.0])
I3 = np.eye(3)
IMAGE = BopImage(0, 0, K, 640, 480)
RZ90 = Rotation.from_euler("z", 90, degrees=True).as_matrix()
NO_SYMMETRY = symmetry_transformations((), ())


def test_errors_are_zero_at_the_true_pose():
    assert mssd(RZ90, t0, RZ90, t0, CUBE, NO_SYMMETRY) == 0.0
    assert mspd(RZ90, t0, RZ90, t0, K, CUBE, NO_SYMMETRY) == 0.0


def test_a_translation_and_a_rotation_give_their_known_errors():
    assert mssd(I3, t0 + [0.01, 0, 0], I3, t0, CUBE, NO_SYMMETRY) == pytest.approx(0.01)
    # 1 cm sideways moves the nearest corners (z = 0.95 m) farthest in the image: 500 * 0.01 / 0.95 px.
    assert mspd(I3, t0 + [0.01, 0, 0], I3, t0, K, CUBE, NO_SYMMETRY) == pytest.approx(5 / 0.95)
    # A turn of 30 degrees about z moves the corners (radius 5 cm * sqrt 2) by the chord 2 r sin 15 degrees.
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    assert mssd(R, t0, I3, t0, CUBE, NO_SYMMETRY) == pytest.approx(2 * 0.05 * np.sqrt(2) * np.sin(np.radians(15)))


def test_a_turn_by_a_symmetry_costs_nothing_and_otherwise_the_full_chord():
    quarter = np.eye(4)
    quarter[:3, :3] = RZ90
    syms = symmetry_transformations((quarter,), ())
    assert len(syms) == 2 and np.array_equal(syms[0][0], I3)
    assert mssd(RZ90, t0, I3, t0, CUBE, syms) == pytest.approx(0.0, abs=1e-12)
    assert mspd(RZ90, t0, I3, t0, K, CUBE, syms) == pytest.approx(0.0, abs=1e-9)
    assert mssd(RZ90, t0, I3, t0, CUBE, NO_SYMMETRY) == pytest.approx(0.1)  # corners turn 90 degrees: chord 10 cm
    assert mspd(RZ90, t0, I3, t0, K, CUBE, NO_SYMMETRY) > 40


def test_continuous_symmetry_is_sampled_finely_and_keeps_its_offset():
    angles = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    ring = np.column_stack([0.05 * np.cos(angles), 0.05 * np.sin(angles), np.zeros(36)])
    offset = np.array([0.02, 0.0, 0.0])  # the axis through (2 cm, 0, 0), along z
    points = ring + offset
    syms = symmetry_transformations((), ({"axis": [0, 0, 1], "offset": offset},))
    assert len(syms) == int(np.ceil(np.pi / 0.01))
    R = Rotation.from_euler("z", 47, degrees=True).as_matrix()
    turned = (R, offset - R @ offset)  # 47 degrees about that axis: the same ring
    R_est, t_est = turned[0], turned[1] + t0
    assert mssd(R_est, t_est, I3, t0, points, syms) < 0.01 * 0.05 * 2  # within the sampling step
    assert mssd(R_est, t_est, I3, t0, points, NO_SYMMETRY) > 0.03


def _square(z: float, cols: slice) -> np.ndarray:
    d = np.zeros((40, 60))
    d[15:25, cols] = z
    return d


def test_vsd_of_a_sideways_shift_is_the_share_outside_the_overlap():
    gt, est = _square(1.0, slice(25, 35)), _square(1.0, slice(27, 37))
    # Union 10 x 12 px, overlap 10 x 8 at equal depth: the 40 px outside it are the error, at every tau.
    assert vsd(est, gt, gt, K, 0.015, FRACTIONS, 0.1) == pytest.approx([40 / 120] * 10)
    assert vsd(gt, gt, gt, K, 0.015, FRACTIONS, 0.1) == [0.0] * 10


def test_vsd_of_a_depth_offset_counts_where_tau_is_below_it():
    gt, est = _square(1.0, slice(25, 35)), _square(1.02, slice(25, 35))
    # 2 cm on a 10 cm diameter is 0.2 (times sqrt(1 + x^2 + y^2) <= 1.0001 near the principal point).
    assert vsd(est, gt, gt, K, 0.015, FRACTIONS, 0.1) == [1.0] * 4 + [0.0] * 6


def test_vsd_ignores_what_an_occluder_hides():
    gt = _square(1.0, slice(25, 35))
    scene = gt.copy()
    scene[15:25, 25:30] = 0.5  # something in front of the left half
    est = _square(1.0, slice(27, 37))
    # Visible of the GT: the right half (10 x 5). The estimate is visible where the scene is not in front of it
    # (cols 30-36) plus where it overlaps the visible GT: union 10 x 7, overlap 10 x 5.
    assert vsd(est, gt, scene, K, 0.015, FRACTIONS, 0.1) == pytest.approx([20 / 70] * 10)
    assert vsd(gt, gt, scene, K, 0.015, FRACTIONS, 0.1) == [0.0] * 10


CUBE_FACES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
)


def _cube(obj_id: int) -> BopObject:
    return BopObject(obj_id, CUBE, CUBE_FACES, float(np.linalg.norm(CUBE[0] - CUBE[-1])), NO_SYMMETRY)


def _estimate(obj_id: int, score: float, t: np.ndarray, R: np.ndarray = I3) -> BopEstimate:
    return BopEstimate(0, 0, obj_id, score, R, t, 0.1)


def test_average_recall_of_a_known_translation_error():
    cube = _cube(1)
    shift = 0.12 * cube.diameter  # MSSD / diameter = 0.12: correct from the threshold 0.15 on
    errors = image_errors(IMAGE, [_estimate(1, 0.9, t0 + [shift, 0, 0])], [(1, I3, t0)], {1: cube})
    ar = average_recall([errors])
    assert ar["kinds"] == ["mssd", "mspd"] and ar["targets"] == 1
    assert ar["ar_mssd"] == pytest.approx(0.8)
    mspd_px = 500 * shift / 0.95  # the nearest corners move farthest
    assert ar["ar_mspd"] == pytest.approx(np.mean([mspd_px < th for th in range(5, 51, 5)]))
    assert ar["ar"] == pytest.approx((ar["ar_mssd"] + ar["ar_mspd"]) / 2)
    # MSPD is scaled to a 640 px wide image: the same poses in a 1280 px image count as half the pixels.
    wide = average_recall([image_errors(BopImage(0, 0, K, 1280, 480), [_estimate(1, 0.9, t0 + [shift, 0, 0])], [(1, I3, t0)], {1: cube})])
    assert wide["ar_mspd"] == pytest.approx(np.mean([mspd_px / 2 < th for th in range(5, 51, 5)]))


def test_only_the_best_scored_estimates_count_and_matching_is_greedy():
    objects = {1: _cube(1), 2: _cube(2)}
    bad, good = t0 + [0.3, 0, 0], t0
    # One instance of object 1: of its two estimates only the best-scored (wrong) one takes part.
    one = image_errors(IMAGE, [_estimate(1, 0.9, bad), _estimate(1, 0.5, good)], [(1, I3, t0)], objects)
    assert average_recall([one])["ar_mssd"] == 0.0
    swapped = image_errors(IMAGE, [_estimate(1, 0.5, bad), _estimate(1, 0.9, good)], [(1, I3, t0)], objects)
    assert average_recall([swapped])["ar_mssd"] == 1.0
    # An estimate of an object without a target takes no part and costs nothing.
    extra = image_errors(IMAGE, [_estimate(1, 0.9, good), _estimate(2, 1.0, good)], [(1, I3, t0)], objects)
    assert list(extra.kept) == [0] and average_recall([extra])["ar"] == 1.0
    # Two instances of one object, a at 0 and b 4 cm aside; the better-scored estimate lies 2.5 cm from a and
    # 1.5 cm from b, the other right on b. Greedy matching gives the first b wherever both are in reach, so the
    # second finds b taken until the threshold reaches a (4 cm); an optimal assignment would match both at 0.15
    # and 0.20 (26 and 35 mm) already.
    a, b = t0, t0 + [0.04, 0, 0]
    two = image_errors(IMAGE, [_estimate(1, 0.9, t0 + [0.025, 0, 0]), _estimate(1, 0.8, b)], [(1, I3, a), (1, I3, b)], objects)
    ar = average_recall([two])
    assert ar["ar_mssd"] == pytest.approx(np.mean([0.5] * 4 + [1.0] * 6))
    assert ar["objects"][1]["targets"] == 2


def test_vsd_enters_average_recall_with_depth(lmo_dir):
    info = load_models_info(lmo_dir / "models_eval" / "models_info.json")[1]
    ape = BopObject.load(lmo_dir / "models_eval", info)
    t = np.array([0.0, 0.0, 0.6])
    scene = ape.depth(I3, t, K, 640, 480)
    assert (scene > 0).sum() > 1000
    right = image_errors(BopImage(0, 0, K, 640, 480, scene), [_estimate(1, 1.0, t)], [(1, I3, t)], {1: ape})
    far = image_errors(BopImage(0, 0, K, 640, 480, scene), [_estimate(1, 1.0, t + [0, 0, 0.05])], [(1, I3, t)], {1: ape})
    assert average_recall([right])["ar_vsd"] == 1.0 and average_recall([right])["kinds"] == ["vsd", "mssd", "mspd"]
    assert average_recall([far])["ar_vsd"] < 0.2  # 5 cm behind is half the diameter: beyond every tau
    assert average_recall([right, far])["ar_vsd"] == pytest.approx(0.5 * (1.0 + average_recall([far])["ar_vsd"]))


def test_results_file_round_trips_in_bop_units(tmp_path):
    R = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    ests = [BopEstimate(2, 7, 5, 0.875, R, np.array([0.01, -0.02, 0.5]), 0.25), BopEstimate(48, 0, 1, 1.0, I3, t0)]
    path = tmp_path / "axispose_lmo-test.csv"
    write_bop_results(path, ests)
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time" and len(lines) == 3
    cells = lines[1].split(",")
    assert cells[:4] == ["2", "7", "5", "0.875"] and len(cells[4].split()) == 9 and cells[6] == "0.25"
    assert [float(v) for v in cells[5].split()] == pytest.approx([10.0, -20.0, 500.0])  # millimetres
    back = read_bop_results(path)
    for a, b in zip(ests, back, strict=True):
        assert (a.scene_id, a.im_id, a.obj_id, a.score, a.time) == (b.scene_id, b.im_id, b.obj_id, b.score, b.time)
        assert np.array_equal(a.R, b.R) and np.allclose(a.t, b.t, rtol=0, atol=1e-15)
    path.write_text("1,2,3\n")
    with pytest.raises(BopFormatError, match="line 1: expected 7"):
        read_bop_results(path)


def test_targets_file_is_read_and_checked(tmp_path):
    path = tmp_path / "test_targets_bop19.json"
    path.write_text(
        json.dumps([{"im_id": 3, "inst_count": 1, "obj_id": 5, "scene_id": 2}, {"im_id": 3, "inst_count": 2, "obj_id": 1, "scene_id": 2}])
    )
    assert load_test_targets(path) == {(2, 3): {5: 1, 1: 2}}
    path.write_text(json.dumps([{"im_id": 3, "obj_id": 5, "scene_id": 2}]))
    with pytest.raises(BopFormatError, match="inst_count"):
        load_test_targets(path)


@pytest.fixture(scope="module")
def depth_scenes(tmp_path_factory, lmo_dir):
    out = tmp_path_factory.mktemp("bopdata")
    generate(SynthConfig(seed=5, scenes=1, images_per_scene=2, objects=(1, 5, 10), depth=True), lmo_dir / "models", out, progress=False)
    return out


def _truth(scene_dir, shift=0.0):
    scene = BopScene(scene_dir)
    frames = iter(scene.image_ids)

    def predict(image, K, boxes):
        gt = {g.obj_id: g for g in scene.gt[next(frames)]}
        return [Prediction(gt[o].R, gt[o].t + [shift, 0, 0], True) for o, _ in boxes]

    return predict


def test_depth_images_hold_the_objects_depth(depth_scenes):
    scene = BopScene(depth_scenes / "000000")
    assert json.loads((depth_scenes / "000000" / "scene_camera.json").read_text())["0"]["depth_scale"] == 0.1
    depth = scene.depth(0)
    assert depth is not None and depth.shape == (480, 640)
    infos = load_models_info(depth_scenes / "models_info.json")
    for k, (g, _) in enumerate(scene.instances(0)):
        visible = cv2.imread(str(depth_scenes / "000000" / "mask_visib" / f"000000_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        radius = 0.5 * infos[g.obj_id].diameter
        assert np.all(np.abs(depth[visible] - g.t[2]) <= radius)  # the object's own surface, to 0.1 mm steps


def test_eval_of_true_poses_has_full_average_recall_and_writes_the_results(depth_scenes, lmo_dir, tmp_path):
    objects = objects_from_models(depth_scenes)
    run = evaluate(_truth(depth_scenes / "000000"), depth_scenes, lmo_dir / "models_eval", objects, EvalOptions(progress=False, bop=True))
    records = run.records
    ar = summarize(records, objects, {}, bop=run.bop)["bop19"]
    assert ar["kinds"] == ["vsd", "mssd", "mspd"] and ar["targets"] == len(records)
    assert ar["ar"] == ar["ar_vsd"] == ar["ar_mssd"] == ar["ar_mspd"] == 1.0
    assert {e["name"] for e in ar["objects"].values()} <= {"ape", "can", "eggbox"}
    run = evaluate(
        _truth(depth_scenes / "000000", shift=0.5), depth_scenes, lmo_dir / "models_eval", objects, EvalOptions(progress=False, bop=True)
    )
    assert summarize(run.records, objects, {}, bop=run.bop)["bop19"]["ar"] == 0.0
    # The command line: the report's AR, the results file, and the targets file that narrows the instances.
    scene = BopScene(depth_scenes / "000000")
    first = scene.gt[0][0].obj_id
    (depth_scenes / "test_targets_bop19.json").write_text(json.dumps([{"scene_id": 0, "im_id": 0, "obj_id": first, "inst_count": 1}]))
    try:
        args = ["eval", "--checkpoint", str(_tiny_checkpoint(depth_scenes, tmp_path)), "--data", str(depth_scenes),
                "--models", str(lmo_dir / "models_eval"), "--report", str(tmp_path / "rep.json"), "--threads", "1",
                "--bop-results", str(tmp_path / "axispose_lmo-test.csv")]  # fmt: skip
        assert main(args) == 0
    finally:
        (depth_scenes / "test_targets_bop19.json").unlink()
    report = json.loads((tmp_path / "rep.json").read_text())
    assert report["bop19"]["targets"] == 1 and set(report["bop19"]["kinds"]) == {"vsd", "mssd", "mspd"}
    assert report["config"]["targets"].endswith("test_targets_bop19.json")
    assert sum(e["n"] for e in report["objects"].values()) == 1
    results = read_bop_results(tmp_path / "axispose_lmo-test.csv")
    assert [(r.scene_id, r.im_id, r.obj_id) for r in results] in ([(0, 0, first)], [])


def _tiny_checkpoint(scenes, tmp_path):
    from conftest import TINY_AGM

    from axispose_core.agm.model import AxisGenerator
    from axispose_core.estimator import Estimator
    from axispose_core.estimator_checkpoint import EstimatorConfig
    from axispose_core.tbm.reader import SHIPPED_READER, load_reader

    reader = load_reader(SHIPPED_READER)
    cfg = EstimatorConfig(agm=TINY_AGM, reader=reader.config, objects=tuple(objects_from_models(scenes)), ddim_steps=1)
    Estimator(cfg, AxisGenerator(cfg.agm), reader).save(tmp_path / "est.safetensors")
    return tmp_path / "est.safetensors"
