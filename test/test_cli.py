from axispose_core.cli import main


def test_geometry_demo_recovers_every_pose(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--seed", "3"]) == 0
    out = capsys.readouterr().out
    assert "driller" in out and "failed" not in out
    rows = [line.split() for line in out.splitlines() if line.split()[:1] and line.split()[1:2] in (["net"], ["line-fit"])]
    assert len(rows) == 16
    assert all(float(r[2]) < 5.0 for r in rows)  # rotation error of a clean axis image, degrees
    assert (tmp_path / "geometry_demo.png").stat().st_size > 10_000
