"""The linux-x64 extension zip: built by scripts/build_extension.py, installed and enabled in Blender."""
import json
import os
import subprocess
import sys
import zipfile

import pytest
from blender_tests.helpers.paths import REPO_ROOT
from packaging.tags import compatible_tags, cpython_tags
from packaging.utils import parse_wheel_filename


LINUX_PLATFORMS = ["manylinux_2_28_x86_64"] + [f"manylinux_2_{v}_x86_64" for v in range(27, 16, -1)] + [
    "manylinux2014_x86_64"]

# Runs in a fresh Python so that Blender's user directories can point at a temporary directory
# (BLENDER_USER_RESOURCES is read when bpy is imported) and the install cannot touch this session.
INSTALL_SCRIPT = """
import json, sys
import bpy
result = bpy.ops.extensions.package_install_files(repo="user_default", filepath=sys.argv[1], enable_on_install=True)
print("RESULT=" + json.dumps({
    "result": sorted(result),
    "extensions_dir": bpy.utils.user_resource("EXTENSIONS"),
    "addons": [addon.module for addon in bpy.context.preferences.addons],
    "exclone_operators": dir(bpy.ops.exclone),
}))
"""


@pytest.fixture(scope="module")
def linux_zip(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    build = subprocess.run(
        [sys.executable, str(REPO_ROOT / "scripts" / "build_extension.py"), "--platforms", "linux-x64",
         "--out", str(out), "--stage-dir", str(tmp_path_factory.mktemp("stage") / "exclone")],
        capture_output=True, text=True)
    assert build.returncode == 0, f"build_extension.py failed:\n{build.stdout}\n{build.stderr}"
    zips = list(out.glob("*.zip"))
    assert [z.name for z in zips] == ["exclone-0.1.0-linux_x64.zip"], build.stdout
    return zips[0]


def wheels_serving(wheels, project, python_version):
    """Wheels of `project` that pip would install on CPython `python_version` on Linux x86-64."""
    compatible = (set(cpython_tags(python_version, platforms=LINUX_PLATFORMS))
                  | set(compatible_tags(python_version, platforms=LINUX_PLATFORMS)))
    found = []
    for wheel in wheels:
        name, _version, _build, tags = parse_wheel_filename(wheel)
        if name == project and tags & compatible:
            found.append(wheel)
    return found


def test_zip_bundles_scipy_opencv_and_cholespy_for_both_pythons_but_never_numpy(linux_zip):
    names = zipfile.ZipFile(linux_zip).namelist()
    wheels = [n.removeprefix("wheels/") for n in names if n.startswith("wheels/") and n.endswith(".whl")]
    assert not [w for w in wheels if parse_wheel_filename(w)[0] == "numpy"], wheels
    for python_version in ((3, 11), (3, 13)):
        for project in ("scipy", "opencv-contrib-python-headless", "cholespy", "threadpoolctl"):
            # Blender installs one wheel per project, so exactly one must fit each Python.
            assert len(wheels_serving(wheels, project, python_version)) == 1, (project, python_version, wheels)
    # the pure-Python threadpoolctl wheel serves both Pythons: bundled once
    assert len([w for w in wheels if parse_wheel_filename(w)[0] == "threadpoolctl"]) == 1, wheels


def test_zip_has_face_models_and_no_caches(linux_zip):
    names = set(zipfile.ZipFile(linux_zip).namelist())
    for model in ("face_landmark.tflite", "face_detection_short_range.tflite", "iris_landmark.tflite",
                  "LICENSE-mediapipe-Apache-2.0.txt"):
        assert f"models/{model}" in names
    assert "__init__.py" in names and "blender_manifest.toml" in names
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc") or n.startswith("tests/")]


def test_zip_holds_no_command_line(linux_zip):
    """The command lines (scripts/) run outside Blender's add-on: none of their modules ships."""
    names = zipfile.ZipFile(linux_zip).namelist()
    stems = {name.rsplit("/", 1)[-1].removesuffix(".py") for name in names if name.endswith(".py")}
    assert not stems & {"batch", "cli", "batch_clone", "track_video", "exclone_cli"}, sorted(stems)
    assert not [n for n in names if n.startswith("scripts/")]
    assert {"blender/files.py", "blender/preview.py", "core/reports.py"} <= set(names)


def test_installed_extension_is_enabled_with_its_operators_and_wheels(linux_zip, tmp_path):
    user_resources = tmp_path / "blender_user"
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(user_resources))
    install = subprocess.run([sys.executable, "-c", INSTALL_SCRIPT, str(linux_zip)],
                             capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    lines = [line for line in install.stdout.splitlines() if line.startswith("RESULT=")]
    assert install.returncode == 0 and lines, f"install failed:\n{install.stdout}\n{install.stderr}"
    report = json.loads(lines[-1].removeprefix("RESULT="))

    assert report["result"] == ["FINISHED"]
    assert report["extensions_dir"].startswith(str(user_resources)), "the real user's extensions were used"
    assert "bl_ext.user_default.exclone" in report["addons"]
    assert "clone_expressions" in report["exclone_operators"], install.stderr
    # Blender unpacks the wheels matching its Python into the extensions' private site-packages.
    python = f"python{sys.version_info[0]}.{sys.version_info[1]}"
    site_packages = user_resources / "extensions" / ".local" / "lib" / python / "site-packages"
    installed = {p.name for p in site_packages.iterdir()} if site_packages.is_dir() else set()
    assert {"scipy", "cv2", "cholespy", "threadpoolctl.py"} <= installed, installed
    assert "numpy" not in installed
