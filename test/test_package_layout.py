"""The ament_python layout: installed the way colcon installs it, the package is found through the ament index."""

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_package_xml_is_format_3_with_the_runtime_dependencies():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "axispose_ros"
    deps = {e.text for e in root.findall("exec_depend")}
    assert {"rclpy", "sensor_msgs", "geometry_msgs", "visualization_msgs", "diagnostic_msgs"} <= deps
    assert root.find("export/build_type").text == "ament_python"


@pytest.fixture(scope="module")
def install_prefix(tmp_path_factory) -> Path:
    """`setup.py build ... install --prefix` with setup.cfg's script dirs: what colcon's ament_python build runs."""
    tmp = tmp_path_factory.mktemp("colcon")
    prefix = tmp / "install"
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    site.mkdir(parents=True)
    env = {**os.environ, "PYTHONPATH": str(site)}
    cmd = [
        sys.executable,
        "setup.py",
        "-q",
        "egg_info",
        "--egg-base",
        str(tmp),
        "build",
        "--build-base",
        str(tmp / "build"),
        "install",
        "--prefix",
        str(prefix),
        "--record",
        str(tmp / "record.txt"),
        "--single-version-externally-managed",
    ]
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return prefix


def _ament(prefix: Path, code: str) -> str:
    env = {**os.environ, "AMENT_PREFIX_PATH": str(prefix)}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


def test_ament_index_finds_the_package_and_its_executables(install_prefix):
    found = _ament(install_prefix, "from ament_index_python.packages import get_package_prefix; print(get_package_prefix('axispose_ros'))")
    assert Path(found) == install_prefix
    share = _ament(install_prefix, "from ament_index_python.packages import get_package_share_directory as g; print(g('axispose_ros'))")
    assert (Path(share) / "package.xml").is_file()
    assert any((Path(share) / "config").glob("*.yaml"))
    # `ros2 run axispose_ros X` executes <prefix>/lib/axispose_ros/X
    for exe in ("axispose_node", "axispose"):
        path = install_prefix / "lib" / "axispose_ros" / exe
        assert path.is_file() and os.access(path, os.X_OK), exe


def test_installed_cli_runs_from_the_prefix(install_prefix):
    site = next((install_prefix / "lib").glob("python*/site-packages"))
    env = {**os.environ, "PYTHONPATH": str(site)}
    proc = subprocess.run(
        [str(install_prefix / "lib" / "axispose_ros" / "axispose"), "--help"], env=env, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0 and "demo" in proc.stdout
    shipped = list(site.glob("axispose_core/models/*.safetensors"))
    assert shipped, "the shipped reader checkpoint must be installed with the package"


def test_node_refuses_a_missing_checkpoint(install_prefix, tmp_path):
    site = next((install_prefix / "lib").glob("python*/site-packages"))
    env = {**os.environ, "PYTHONPATH": f"{site}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", "ROS_LOG_DIR": str(tmp_path)}
    exe = str(install_prefix / "lib" / "axispose_ros" / "axispose_node")
    missing = tmp_path / "none.safetensors"
    proc = subprocess.run([exe, "--ros-args", "-p", f"checkpoint:={missing}"], env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "checkpoint file not found" in proc.stderr
