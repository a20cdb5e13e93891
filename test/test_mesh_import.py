import numpy as np
import pytest

from axispose_core.cli import main
from axispose_core.data.bop import BopFormatError, BopScene, load_models_info, model_path
from axispose_core.data.mesh_import import import_meshes
from axispose_core.data.meshes import load_obj, load_ply
from axispose_core.data.synth.config import SynthConfig, recipe

CUBE_OBJ = """# a 4 cm cube in millimetres, wound counter-clockwise seen from outside, with vertex colours
v -20 -20 -20 1 0 0
v 20 -20 -20 0 1 0
v 20 20 -20 0 0 1
v -20 20 -20 1 1 0
v -20 -20 20 1 0 1
v 20 -20 20 0 1 1
v 20 20 20 1 1 1
v -20 20 20 0.2 0.2 0.2
f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 2 3 7 6
f 3 4 8 7
f 4 1 5 8
"""


def test_obj_quads_are_triangulated_with_colours(tmp_path):
    p = tmp_path / "cube.obj"
    p.write_text(CUBE_OBJ)
    mesh = load_obj(p)
    assert mesh.faces.shape == (12, 3)
    assert mesh.vertices.max() == pytest.approx(0.02)
    assert tuple(mesh.colors[0]) == (255, 0, 0)


def test_import_writes_a_bop_models_folder(tmp_path, lmo_dir):
    cube = tmp_path / "cube.obj"
    cube.write_text(CUBE_OBJ)
    ids = import_meshes([cube, model_path(lmo_dir / "models", 1)], tmp_path / "models")
    assert list(ids) == [1, 2]
    infos = load_models_info(tmp_path / "models" / "models_info.json")
    assert infos[1].diameter == pytest.approx(0.04 * np.sqrt(3))
    assert infos[2].diameter == pytest.approx(0.102099, rel=0.01)  # the LM-O ape, recomputed
    again = load_ply(model_path(tmp_path / "models", 2))
    np.testing.assert_allclose(again.vertices, load_ply(model_path(lmo_dir / "models", 1)).vertices, atol=1e-7)
    assert again.colors is not None


def test_bad_obj_is_refused(tmp_path):
    p = tmp_path / "bad.obj"
    p.write_text("v 1 2\nf 1 2 3\n")
    with pytest.raises(BopFormatError, match=r"bad\.obj:1"):
        load_obj(p)
    with pytest.raises(BopFormatError, match="unsupported"):
        import_meshes([tmp_path / "x.stl"], tmp_path / "m")


def test_synth_from_user_meshes(tmp_path):
    cube = tmp_path / "cube.obj"
    cube.write_text(CUBE_OBJ)
    out = tmp_path / "data"
    args = ["synth", "--models", str(cube), "--out", str(out), "--scenes", "1", "--images-per-scene", "2", "--seed", "3"]
    assert main(args) == 0
    scene = BopScene(out / "000000")
    assert {g.obj_id for insts in scene.gt.values() for g in insts} == {1}
    assert any(i.visib_fract > 0 for infos in scene.gt_info.values() for i in infos)
    saved = SynthConfig.load(out / "synth_config.json")  # the default recipe is the desk
    assert (saved.scene, saved.randomization) == recipe("desk")
