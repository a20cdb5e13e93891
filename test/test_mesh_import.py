import numpy as np
import pytest

from axispose_core.cli import main
from axispose_core.data.bop import BopFormatError
from axispose_core.data.bop_models import load_models_info, model_path
from axispose_core.data.bop_scene import BopScene
from axispose_core.data.mesh_import import import_meshes
from axispose_core.data.meshes import load_obj, load_ply
from axispose_core.data.synth.config import SynthConfig, recipe
from axispose_core.objects import objects_from_models

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


def _two_colour_texture(path):
    """A 64 x 64 texture: red left half, blue right half (PNG, so the test reads exact colours)."""
    import cv2

    image = np.zeros((64, 64, 3), np.uint8)
    image[:, :32] = (0, 0, 255)  # BGR red
    image[:, 32:] = (255, 0, 0)  # BGR blue
    cv2.imwrite(str(path), image)


def test_textured_obj_takes_its_colours_from_the_texture(tmp_path):
    """Two quads of one plane, each mapped onto one half of a two-colour texture (map_Kd), a third quad with a
    plain Kd material: every vertex gets the colour under its UV, faces are split down to a few texels, and the
    shape is unchanged."""
    _two_colour_texture(tmp_path / "tex.png")
    (tmp_path / "quads.mtl").write_text("newmtl textured\nKd 0.5 0.5 0.5\nmap_Kd tex.png\nnewmtl green\nKd 0 1 0\n")
    (tmp_path / "quads.obj").write_text(
        "mtllib quads.mtl\n"
        "v 0 0 0\nv 10 0 0\nv 10 10 0\nv 0 10 0\nv 20 0 0\nv 20 10 0\nv 30 0 0\nv 30 10 0\n"
        "vt 0.05 0.05\nvt 0.45 0.05\nvt 0.45 0.95\nvt 0.05 0.95\nvt 0.55 0.05\nvt 0.95 0.05\nvt 0.95 0.95\nvt 0.55 0.95\n"
        "usemtl textured\nf 1/1 2/2 3/3 4/4\nf 2/5 5/6 6/7 3/8\nusemtl green\nf 5 7 8 6\n"
    )  # fmt: skip
    mesh = load_obj(tmp_path / "quads.obj")
    assert len(mesh.faces) > 6 and mesh.colors is not None  # the textured quads were split
    x = mesh.vertices[:, 0] / 0.001
    left, right, green = x < 9.99, (x > 10.01) & (x < 19.99), x > 20.01
    assert (mesh.colors[left] == (255, 0, 0)).all() and (mesh.colors[right] == (0, 0, 255)).all()
    assert (mesh.colors[green] == (0, 255, 0)).all()
    area = 0.5 * np.linalg.norm(np.cross(*(mesh.vertices[mesh.faces[:, k]] - mesh.vertices[mesh.faces[:, 0]] for k in (1, 2))), axis=1)
    assert area.sum() == pytest.approx(0.03 * 0.01)  # split, not changed


def test_textured_ply_with_per_vertex_uvs(tmp_path):
    import plyfile

    _two_colour_texture(tmp_path / "tex.png")
    rows = [
        (0, 0, 0, 0.1, 0.5),
        (10, 0, 0, 0.4, 0.5),
        (0, 10, 0, 0.1, 0.9),
        (20, 0, 0, 0.6, 0.5),
        (30, 0, 0, 0.9, 0.5),
        (20, 10, 0, 0.6, 0.9),
    ]
    v = np.array(rows, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("texture_u", "f4"), ("texture_v", "f4")])
    f = np.array([([0, 1, 2],), ([3, 4, 5],)], dtype=[("vertex_indices", "i4", (3,))])
    ply = plyfile.PlyData(
        [plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(f, "face")], comments=["TextureFile tex.png"]
    )
    ply.write(str(tmp_path / "two.ply"))
    mesh = load_ply(tmp_path / "two.ply")
    x = mesh.vertices[:, 0] / 0.001
    assert (mesh.colors[x < 10.01] == (255, 0, 0)).all() and (mesh.colors[x > 19.99] == (0, 0, 255)).all()
    (tmp_path / "none.ply").write_bytes((tmp_path / "two.ply").read_bytes().replace(b"texture_u", b"texture_a"))
    with pytest.raises(BopFormatError, match="no texture coordinates"):
        load_ply(tmp_path / "none.ply")


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


def test_symmetry_is_declared_at_import(tmp_path, capsys):
    cube, ape = tmp_path / "cube.obj", tmp_path / "ape.obj"
    cube.write_text(CUBE_OBJ)
    ape.write_text(CUBE_OBJ)
    import_meshes([cube, ape], tmp_path / "models", symmetries={"cube": "4-z", "ape": "continuous-x"})
    infos = load_models_info(tmp_path / "models" / "models_info.json")
    assert len(infos[1].symmetries_discrete) == 3 and not infos[1].symmetries_continuous  # turns of 90, 180, 270 degrees
    np.testing.assert_allclose(infos[1].symmetries_discrete[0][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(infos[2].symmetries_continuous[0]["axis"], [1, 0, 0])
    assert all(o.symmetric for o in objects_from_models(tmp_path / "models"))
    for spec, message in (({"cube": "3-w"}, "expected continuous-AXIS"), ({"mug": "2-z"}, "not among the imported")):
        with pytest.raises(BopFormatError, match=message):
            import_meshes([cube], tmp_path / "other", symmetries=spec)
    args = ["synth", "--models", str(cube), str(ape), "--out", str(tmp_path / "data"), "--scenes", "1", "--images-per-scene", "1"]
    assert main([*args, "--symmetry", "cube=1-z"]) == 2
    assert "expected continuous-AXIS or N-AXIS" in capsys.readouterr().err


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


def test_a_ply_read_again_is_the_same_mesh_unless_the_file_changed(tmp_path):
    """load_ply parses a file version once a process: the caller gets its own arrays each time, and a rewritten
    file is read anew."""
    import os

    from axispose_core.data.meshes import Mesh, write_ply

    path = tmp_path / "tri.ply"
    tri = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]), np.full((3, 3), 7, np.uint8))
    write_ply(path, tri)
    first = load_ply(path)
    first.vertices[0, 0] = 99.0  # the caller's copy
    again = load_ply(path)
    assert again.vertices[0, 0] == 0.0 and np.array_equal(again.faces, tri.faces) and np.array_equal(again.colors, tri.colors)
    assert again.vertices[1, 0] == pytest.approx(1.0) and load_ply(path, units=1.0).vertices[1, 0] == pytest.approx(1000.0)
    write_ply(path, Mesh(tri.vertices * 2, tri.faces, tri.colors))
    os.utime(path, ns=(1, 1))  # another version, even within the clock's resolution
    assert load_ply(path).vertices[1, 0] == pytest.approx(2.0)
