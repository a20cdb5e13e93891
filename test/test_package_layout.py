"""The ament_python layout: installed the way colcon installs it, the package is found through the ament index."""

import ast
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


ROSDEP_KEYS = {
    "rclpy": "rclpy", "rcl_interfaces": "rcl_interfaces", "std_msgs": "std_msgs", "sensor_msgs": "sensor_msgs",
    "geometry_msgs": "geometry_msgs", "visualization_msgs": "visualization_msgs", "diagnostic_msgs": "diagnostic_msgs",
    "ament_index_python": "ament_index_python", "numpy": "python3-numpy", "scipy": "python3-scipy", "cv2": "python3-opencv",
    "torch": "python3-torch", "safetensors": "python3-safetensors", "plyfile": "python3-plyfile", "yaml": "python3-yaml",
    "tqdm": "python3-tqdm", "matplotlib": "python3-matplotlib", "rosbags": "python3-rosbags-pip", "skimage": "python3-skimage",
    "axispose_msgs": "axispose_msgs", "nav_msgs": "nav_msgs",
}  # fmt: skip
"""The rosdep key of each third-party module the package may import."""


def _imported_modules() -> set[str]:
    """Top-level modules the installed packages import (absolute imports, standard library and own packages left out)."""
    mods = set()
    for path in [*(REPO / "axispose_core").rglob("*.py"), *(REPO / "axispose_ros").rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                mods |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                mods.add(node.module.split(".")[0])
    # Packages read for their data files (the synthetic backgrounds' photographs), imported by name at run time.
    from axispose_core.data.synth.config import ALL_PHOTOS

    mods |= {"skimage"} | {p.split(":")[0] for p in ALL_PHOTOS if ":" in p}
    return {m for m in mods if m not in sys.stdlib_module_names and m not in ("axispose_core", "axispose_ros")}


def test_package_xml_is_format_3_and_declares_exactly_what_the_code_imports():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "axispose_ros"
    assert root.find("export/build_type").text == "ament_python"
    imported = _imported_modules()
    unmapped = sorted(imported - set(ROSDEP_KEYS))
    assert not unmapped, f"imported without a known rosdep key: {unmapped} (add the key to package.xml and ROSDEP_KEYS)"
    declared = {e.text for e in root.findall("exec_depend")} | {e.text for e in root.findall("depend")}
    needed = {ROSDEP_KEYS[m] for m in imported}
    assert not needed - declared, f"imported but not declared in package.xml: {sorted(needed - declared)}"
    # ament_index_python is how the installed package finds its share/ files (setup.py data_files), even if not imported
    assert not declared - needed - {"ament_index_python"}, f"declared but never imported: {sorted(declared - needed)}"


def test_the_message_package_generates_every_message_it_holds():
    """axispose_msgs: an ament_cmake interface package whose CMakeLists generates exactly the files in msg/."""
    root = ET.parse(REPO / "axispose_msgs" / "package.xml").getroot()
    assert root.get("format") == "3" and root.findtext("name") == "axispose_msgs"
    assert root.find("export/build_type").text == "ament_cmake"
    assert root.findtext("member_of_group") == "rosidl_interface_packages"
    assert {e.text for e in root.findall("depend")} == {"geometry_msgs", "std_msgs"}
    cmake = (REPO / "axispose_msgs" / "CMakeLists.txt").read_text()
    listed = set(re.findall(r'"(msg/\w+\.msg)"', cmake))
    assert listed == {f"msg/{p.name}" for p in (REPO / "axispose_msgs" / "msg").glob("*.msg")}
    from axispose_msgs.msg import Detection, DetectionArray  # built and installed by `make test` (tools/build_msgs.sh)

    assert DetectionArray.get_fields_and_field_types() == {"header": "std_msgs/Header", "detections": "sequence<axispose_msgs/Detection>"}
    assert set(Detection.get_fields_and_field_types()) == {"obj_id", "name", "track_id", "score", "pose", "box"}


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
    # the installed node finds its Fast DDS profile through the index (no config/ beside the installed sources)
    site = next((install_prefix / "lib").glob("python*/site-packages"))
    code = f"import sys; sys.path.insert(0, {str(site)!r}); from axispose_ros.node import shipped_fastdds_profile as s; print(s())"
    assert Path(_ament(install_prefix, code)) == Path(share) / "config" / "fastdds_profile.xml"
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


def _core_import_graph() -> dict[str, set[str]]:
    """axispose_core's modules and the core modules each imports, at any depth of the file (an import inside a
    function is a dependency too: deferring it hides a circle, it does not remove it)."""
    root = REPO / "axispose_core"
    names = {".".join(p.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__"): p for p in root.rglob("*.py")}
    graph = {}
    for name, path in names.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("axispose_core"):
                deps |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in names else node.module for a in node.names}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith("axispose_core")}
        graph[name] = {d for d in deps if d in names and d != name}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of the graph, or None (depth-first search, grey/black marking)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for dep in sorted(graph[node]):
            if state.get(dep) == 1:
                return stack[stack.index(dep) :] + [dep]
            if dep not in state and (found := visit(dep)):
                return found
        stack.pop()
        state[node] = 2
        return None

    return next((c for n in sorted(graph) if n not in state and (c := visit(n))), None)


def test_axispose_core_has_no_import_circle_and_never_imports_ros():
    graph = _core_import_graph()
    assert len(graph) > 50 and "axispose_core.data.bop" in graph["axispose_core.data.meshes"]  # the graph is read
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]  # the search finds a circle
    cycle = _cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)
    ros = ("rclpy", "axispose_ros", "axispose_msgs", "sensor_msgs", "std_msgs", "geometry_msgs")
    for path in (REPO / "axispose_core").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            mods = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            assert not [m for m in mods if m.split(".")[0] in ros], f"{path} imports ROS ({mods})"
    # the BOP readers never render
    readers = [m for m in graph if m.startswith("axispose_core.data.bop")]
    assert not {d for m in readers for d in graph[m] if ".synth." in d or d.endswith(("visibility", "meshes"))}


def _wide_or_long(tree: ast.AST, most_lines: int, most_params: int) -> list[str]:
    """Functions over `most_lines` lines or `most_params` parameters (self/cls not counted), argparse builders
    aside (a parser's options are its content)."""
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) or "parser" in node.name:
            continue
        a = node.args
        params = [*a.posonlyargs, *a.args, *a.kwonlyargs, *([a.vararg] if a.vararg else []), *([a.kwarg] if a.kwarg else [])]
        n = len([p for p in params if p.arg not in ("self", "cls")])
        lines = node.end_lineno - node.lineno + 1
        if lines > most_lines or n > most_params:
            found.append(f"{node.name} ({lines} lines, {n} parameters)")
    return found


def test_coordinators_stay_narrow():
    """Functions read as their steps: none over 80 lines or 8 parameters; the node wires its parts in ≤ 150 lines."""
    assert _wide_or_long(ast.parse("def f(a, b, c):\n    pass\n"), 1, 2) == ["f (2 lines, 3 parameters)"]  # it counts
    offenders = {}
    for package in ("axispose_core", "axispose_ros"):
        for path in sorted((REPO / package).rglob("*.py")):
            if found := _wide_or_long(ast.parse(path.read_text(), str(path)), 80, 8):
                offenders[str(path.relative_to(REPO))] = found
    assert not offenders, f"functions to split or whose parameters to group: {offenders}"
    node = next(n for n in ast.parse((REPO / "axispose_ros" / "node.py").read_text()).body if getattr(n, "name", "") == "AxisPoseNode")
    assert node.end_lineno - node.lineno + 1 <= 150, "AxisPoseNode grew past 150 lines: move a part into a module of its own"


def test_modules_hold_one_thing():
    """A module over 450 lines holds more than one thing: split it by what it holds. The README, the front door,
    stays within 170 lines (the rest of the reference lives in docs/)."""
    long = {}
    for package in ("axispose_core", "axispose_ros"):
        for path in sorted((REPO / package).rglob("*.py")):
            if (n := len(path.read_text().splitlines())) > 450:
                long[str(path.relative_to(REPO))] = n
    assert not long, f"modules over 450 lines: {long}"
    assert len((REPO / "README.md").read_text().splitlines()) <= 170


def test_tbm_never_reaches_back_into_the_agm():
    """The data flow runs AGM -> axis image -> reader -> back-projection: the TBM imports nothing of the AGM."""
    graph = _core_import_graph()
    tbm = {m: deps for m, deps in graph.items() if m.startswith("axispose_core.tbm")}
    back = {m: sorted(d for d in deps if d.startswith("axispose_core.agm")) for m, deps in tbm.items()}
    assert not any(back.values()), f"tbm imports agm: {back}"


def test_the_node_loads_no_data_or_training_code():
    """The node runs the estimator: readers of datasets, the synthetic-data package and the trainers stay out."""
    pkgs = "('axispose_core.data', 'axispose_core.train')"
    code = f"import sys, axispose_ros.node; print(*sorted(m for m in sys.modules if m.startswith({pkgs})))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert out.stdout.strip() == ""


def test_the_docs_describe_the_product_not_its_history():
    """BENCHMARKS holds the shipped model's numbers and one row per design comparison, the model card the model;
    the history of runs lives in git."""
    limits = {"BENCHMARKS.md": 400, "MODEL_CARD.md": 120}
    for name, most in limits.items():
        text = (REPO / "docs" / name).read_text()
        assert len(text.splitlines()) <= most, f"docs/{name}: {len(text.splitlines())} lines, at most {most}"
        assert not re.search(r"\b(phase|session)s?\b", text, re.IGNORECASE), f"docs/{name} tells its history"
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        dated = [line for line in path.read_text().splitlines() if line.startswith("#") and re.search(r"\b20\d\d-\d\d-\d\d\b", line)]
        assert not dated, f"{path.name}: dated headings {dated}"


def test_shipped_files_stay_small():
    """Every committed version of a shipped file stays in every clone for ever: the shipped model files (weights,
    demo bag) are kept to 20 MB each, and a checkpoint is committed only when it ships."""
    tracked = subprocess.run(["git", "ls-files", "-z", "axispose_core/models", "demo"], cwd=REPO, capture_output=True, check=True)
    files = [REPO / f for f in tracked.stdout.decode().split("\0") if f]
    assert files, "no shipped files found by git ls-files"
    large = {str(f.relative_to(REPO)): f.stat().st_size for f in files if f.stat().st_size > 20 * 2**20}
    assert not large, f"shipped files over 20 MB: {large}"
