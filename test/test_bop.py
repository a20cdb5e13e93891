import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from axispose_core.cli import main
from axispose_core.data.bop import (
    MM,
    ROTATION_TOL,
    BopFormatError,
    GTInfo,
    GTInstance,
    bbox_from_model,
    load_camera_poses,
    load_scene_camera,
    load_scene_gt,
    read_scene_gt,
    write_scene_camera,
    write_scene_gt,
    write_scene_gt_info,
)
from axispose_core.data.bop_models import load_models_info, model_path, write_models_info
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.meshes import load_ply
from axispose_core.data.visibility import gt_info_from_models, write_gt_info
from axispose_core.lmo import LMO_DIAMETERS, LMO_K, LMO_SYMMETRIC
from axispose_core.objects import objects_from_models


def test_lmo_models_info_in_metres_with_symmetries(lmo_dir):
    infos = load_models_info(lmo_dir / "models" / "models_info.json")
    assert sorted(infos) == [1, 5, 6, 8, 9, 10, 11, 12]
    assert infos[1].diameter == pytest.approx(0.102099)
    assert {i for i, info in infos.items() if info.symmetric} == set(LMO_SYMMETRIC)
    T = infos[10].symmetries_discrete[0]
    assert T[:3, 3] == pytest.approx([0.232611 * MM, 0.694388 * MM, -0.0792063 * MM])
    for i, d in LMO_DIAMETERS.items():  # the embedded copy agrees with the dataset
        assert infos[i].diameter == pytest.approx(d, abs=1e-6)


def test_lmo_models_load_with_colours_in_metres(lmo_dir):
    mesh = load_ply(model_path(lmo_dir / "models", 1))
    assert mesh.colors is not None and mesh.colors.shape == mesh.vertices.shape
    assert mesh.faces.shape[1] == 3 and mesh.faces.max() < len(mesh.vertices)
    extent = np.ptp(mesh.vertices, axis=0)
    assert extent == pytest.approx([0.0759, 0.0776, 0.0918], abs=2e-3)
    assert load_ply(model_path(lmo_dir / "models_eval", 1)).colors is None  # binary, decimated


def test_objects_from_models(lmo_dir):
    objs = objects_from_models(lmo_dir / "models", [1, 10], {1: "ape", 10: "eggbox"})
    assert [o.name for o in objs] == ["ape", "eggbox"]
    assert objs[0].scale == pytest.approx(0.5 * 0.102099) and objs[1].symmetric
    with pytest.raises(ValueError, match="no object"):
        objects_from_models(lmo_dir / "models", [99])


def _scene(tmp_path, rng):
    gt, cams, infos = {}, {}, {}
    for im_id in range(3):
        insts = []
        for obj_id in (1, 5):
            R = Rotation.random(random_state=rng).as_matrix()
            insts.append(GTInstance(obj_id, R, np.array([0.01 * im_id, -0.02, 0.8])))
        gt[im_id] = insts
        cams[im_id] = LMO_K
        infos[im_id] = [GTInfo((10, 20, 30, 40), (12, 22, 20, 30), 1200, 1200, 600, 0.5)] * 2
    write_scene_gt(tmp_path / "scene_gt.json", gt)
    write_scene_camera(tmp_path / "scene_camera.json", cams)
    write_scene_gt_info(tmp_path / "scene_gt_info.json", infos)
    return gt


def test_scene_round_trip_keeps_metres(tmp_path, rng):
    gt = _scene(tmp_path, rng)
    raw = json.loads((tmp_path / "scene_gt.json").read_text())
    assert raw["1"][0]["cam_t_m2c"] == pytest.approx([10.0, -20.0, 800.0])  # mm on disk
    scene = BopScene(tmp_path)
    assert scene.image_ids == [0, 1, 2]
    np.testing.assert_allclose(scene.gt[2][1].R, gt[2][1].R)
    np.testing.assert_allclose(scene.gt[2][1].t, gt[2][1].t)
    np.testing.assert_allclose(scene.cameras[0], LMO_K)
    assert [info.bbox_obj for _, info in scene.instances(1)] == [(10, 20, 30, 40)] * 2
    pairs = scene.instances(2)
    assert [g.obj_id for g, _ in pairs] == [1, 5] and [info.visib_fract for _, info in pairs] == [0.5, 0.5]


def test_camera_poses_round_trip_in_mm_where_given_and_a_non_rotation_is_refused(tmp_path, rng):
    """BOP's optional world-to-camera pose per image: metres in memory, mm on disk, only the images that have one."""
    _scene(tmp_path, rng)
    assert BopScene(tmp_path).camera_poses == {}
    R = Rotation.random(random_state=rng).as_matrix()
    write_scene_camera(tmp_path / "scene_camera.json", {i: LMO_K for i in range(3)}, poses={1: (R, np.array([0.1, 0.0, -0.5]))})
    raw = json.loads((tmp_path / "scene_camera.json").read_text())
    assert raw["1"]["cam_t_w2c"] == pytest.approx([100.0, 0.0, -500.0]) and "cam_R_w2c" not in raw["0"]
    poses = BopScene(tmp_path).camera_poses
    assert list(poses) == [1]
    np.testing.assert_allclose(poses[1][0], R, atol=1e-12)
    np.testing.assert_allclose(poses[1][1], [0.1, 0.0, -0.5])
    raw["1"]["cam_R_w2c"] = [2, 0, 0, 0, 1, 0, 0, 0, 1]
    (tmp_path / "scene_camera.json").write_text(json.dumps(raw))
    with pytest.raises(BopFormatError, match=r"cam_R_w2c.*not a rotation"):
        load_camera_poses(tmp_path / "scene_camera.json")


def test_boxes_and_visibility_from_models_when_gt_info_is_absent(tmp_path, lmo_dir):
    # The ape a little in front of the can and beside it: it hides part of the can, which hides none of it.
    gt = {0: [GTInstance(1, np.eye(3), np.array([0.0, 0.0, 0.7])), GTInstance(5, np.eye(3), np.array([0.03, 0.0, 0.85]))]}
    write_scene_gt(tmp_path / "scene_gt.json", gt)
    write_scene_camera(tmp_path / "scene_camera.json", {0: LMO_K})
    (tmp_path / "rgb").mkdir()
    cv2.imwrite(str(tmp_path / "rgb" / "000000.png"), np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(BopFormatError, match=r"no scene_gt_info\.json; write it with `axispose gt-info"):
        BopScene(tmp_path).instances(0)
    scene = BopScene(tmp_path, gt_info_from_models(lmo_dir / "models_eval"))
    assert scene.visibility_estimated
    (_, i1), (g5, i5) = scene.instances(0)
    # `axispose gt-info` writes the same values into the scene, once; the reader then reads them without models.
    assert main(["gt-info", str(tmp_path), "--models", str(lmo_dir / "models_eval")]) == 0
    read = BopScene(tmp_path)
    assert not read.visibility_estimated and read.instances(0)[1][1].bbox_obj == i5.bbox_obj
    assert read.instances(0)[1][1].px_count_visib == i5.px_count_visib
    assert not write_gt_info(tmp_path, lmo_dir / "models_eval")  # kept unless asked to overwrite
    pts = load_ply(model_path(lmo_dir / "models_eval", 5)).vertices
    assert i5.bbox_obj == bbox_from_model(LMO_K, g5.R, g5.t, pts)
    assert i1.visib_fract == 1.0 and 0.3 < i5.visib_fract < 0.95, (i1.visib_fract, i5.visib_fract)
    assert i5.px_count_visib < i5.px_count_all == i5.px_count_valid
    x, _, w, _ = i5.bbox_visib
    assert i5.bbox_obj[0] <= x and x + w <= i5.bbox_obj[0] + i5.bbox_obj[2] + 1


def test_rotations_a_little_off_orthonormal_are_projected_and_counted(tmp_path, caplog):
    from conftest import OFF_ORTHONORMAL

    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    off = R @ (np.eye(3) + OFF_ORTHONORMAL)  # as the official LM-O GT: |RR^T - I| 0.0093, det 1.014
    entries = [{"cam_R_m2c": m.ravel().tolist(), "cam_t_m2c": [0, 0, 800], "obj_id": 1} for m in (off, R)]
    (tmp_path / "scene_gt.json").write_text(json.dumps({"0": entries}))
    with caplog.at_level("WARNING"):
        gt = read_scene_gt(tmp_path / "scene_gt.json")
    assert gt.projected == 1 and 0.009 < gt.worst < ROTATION_TOL
    fixed = gt.instances[0][0].R
    np.testing.assert_allclose(fixed @ fixed.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(fixed) == pytest.approx(1.0)
    assert np.degrees(np.arccos((np.trace(fixed.T @ R) - 1) / 2)) < 1.0  # the rotation meant
    np.testing.assert_array_equal(gt.instances[0][1].R, R)  # an exact rotation is left as it is
    assert "1 GT rotations were not orthonormal" in caplog.text
    for bad in (R @ np.diag([1.0, 1.0, 1.04]), R @ np.diag([1.0, 1.0, -1.0])):  # past the tolerance; a reflection
        entries[0]["cam_R_m2c"] = bad.ravel().tolist()
        (tmp_path / "scene_gt.json").write_text(json.dumps({"0": entries}))
        with pytest.raises(BopFormatError, match="not a rotation matrix"):
            read_scene_gt(tmp_path / "scene_gt.json")


def test_rgb_reads_rgb_and_refuses_an_unreadable_file(tmp_path, rng):
    _scene(tmp_path, rng)
    (tmp_path / "rgb").mkdir()
    bgr = np.zeros((4, 6, 3), np.uint8)
    bgr[..., 0] = 255  # blue in OpenCV's channel order
    cv2.imwrite(str(tmp_path / "rgb" / "000000.png"), bgr)
    (tmp_path / "rgb" / "000001.png").write_bytes(b"not a png")
    scene = BopScene(tmp_path)
    rgb = scene.rgb(0)
    assert rgb.shape == (4, 6, 3) and rgb.dtype == np.uint8 and (rgb[..., 2] == 255).all() and (rgb[..., 0] == 0).all()
    with pytest.raises(BopFormatError, match=r"000001\.png: unreadable image"):
        scene.rgb(1)
    with pytest.raises(BopFormatError, match="no image file for image 2"):
        scene.rgb(2)


def test_models_info_round_trip(tmp_path, lmo_dir):
    infos = load_models_info(lmo_dir / "models" / "models_info.json")
    write_models_info(tmp_path / "models_info.json", infos)
    again = load_models_info(tmp_path / "models_info.json")
    assert again[11].diameter == pytest.approx(infos[11].diameter)
    np.testing.assert_allclose(again[11].symmetries_discrete[0], infos[11].symmetries_discrete[0])


@pytest.mark.parametrize(
    "content, message",
    [
        ('{"0": [{"cam_R_m2c": [1, 0, 0], "cam_t_m2c": [0, 0, 1], "obj_id": 1}]}', "image 0 instance 0: field 'cam_R_m2c'"),
        ('{"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "obj_id": 1}]}', "missing field 'cam_t_m2c'"),
        ('{"0": [{"cam_R_m2c": [2, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 1], "obj_id": 1}]}', "not a rotation"),
        ('{"x": []}', "not an integer id"),
        ("{not json", "not valid JSON"),
    ],
)
def test_bad_scene_gt_names_file_and_field(tmp_path, content, message):
    p = tmp_path / "scene_gt.json"
    p.write_text(content)
    with pytest.raises(BopFormatError, match=message) as err:
        load_scene_gt(p)
    assert str(p) in str(err.value)


def test_bad_camera_is_refused(tmp_path):
    p = tmp_path / "scene_camera.json"
    p.write_text('{"0": {"cam_K": [0, 0, 0, 0, 0, 0, 0, 0, 1]}}')
    with pytest.raises(BopFormatError, match=r"cam_K.*focal"):
        load_scene_camera(p)


def test_missing_file_and_broken_ply(tmp_path):
    with pytest.raises(BopFormatError, match="not found"):
        load_scene_gt(tmp_path / "nope.json")
    bad = tmp_path / "obj_000001.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\nzzz\n")
    with pytest.raises(BopFormatError, match=r"obj_000001\.ply"):
        load_ply(bad)


def test_camera_json_gives_K_and_image_size_or_says_what_is_wrong(lmo_dir, tmp_path):
    from axispose_core.data.bop import load_camera

    K, width, height = load_camera(lmo_dir / "camera.json")
    assert np.allclose(K, LMO_K) and (width, height) == (640, 480)
    bad = tmp_path / "camera.json"
    bad.write_text(json.dumps({"fx": 500.0, "fy": 500.0, "cx": 320.0}))
    with pytest.raises(BopFormatError, match="missing field 'cy'"):
        load_camera(bad)
    bad.write_text(json.dumps({"fx": -500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0}))
    with pytest.raises(BopFormatError, match=r"camera\.json"):
        load_camera(bad)
    bad.write_text(json.dumps({"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0, "width": "640"}))
    with pytest.raises(BopFormatError, match="width and height"):
        load_camera(bad)
    bad.write_text(json.dumps({"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0}))
    assert load_camera(bad)[1:] == (None, None)


def test_object_names_come_from_the_models_folder(lmo_dir, tmp_path):
    import shutil

    from axispose_core.objects import NAMES_FILE, dataset_objects, object_names

    assert object_names(lmo_dir / "models")[1] == "ape"  # LM-O's models: LM-O's names
    own = tmp_path / "own"
    own.mkdir()
    info = json.loads((lmo_dir / "models" / "models_info.json").read_text())
    (own / "models_info.json").write_text(json.dumps({"1": info["1"] | {"diameter": 55.0}}))
    assert object_names(own) == {} and objects_from_models(own)[0].name == "obj_000001"  # not 'ape': another object
    (own / NAMES_FILE).write_text(json.dumps({"1": "mug"}))
    assert objects_from_models(own)[0].name == "mug"
    (own / NAMES_FILE).write_text(json.dumps({"1": "my mug"}))
    with pytest.raises(ValueError, match="my mug"):
        object_names(own)
    # Training on several folders reads the objects of all of them; one id with two sizes is refused.
    lmo = tmp_path / "lmo"
    lmo.mkdir()
    shutil.copy(lmo_dir / "models" / "models_info.json", lmo)
    (own / NAMES_FILE).write_text(json.dumps({"1": "mug"}))
    (own / "models_info.json").write_text(json.dumps({"20": info["1"]}))
    assert [(o.obj_id, o.name) for o in dataset_objects([lmo, own])][-2:] == [(12, "holepuncher"), (20, "obj_000020")]
    (own / "models_info.json").write_text(json.dumps({"1": info["1"] | {"diameter": 55.0}}))
    with pytest.raises(ValueError, match="object 1 has diameter"):
        dataset_objects([lmo, own])
