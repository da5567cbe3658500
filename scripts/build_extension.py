"""Build ExClone's installable Blender extension zips, one per platform.

    .venv/bin/python scripts/build_extension.py [--platforms linux-x64,windows-x64,macos-arm64,macos-x64]
                                                [--out dist/] [--stage-dir build/]

Stages exclone_addon/ (without caches and tests) and blender_manifest.toml into the stage directory, adds
the scipy and opencv-contrib-python-headless wheels pinned in requirements.txt (Python 3.11 = Blender 4.2
to 5.0) and requirements-py313.txt (Python 3.13 = Blender 5.1+) for every requested platform, plus the
optional packages pinned below (cholespy, threadpoolctl) wherever a wheel exists, then runs the
extension CLI that ships in the bpy wheel (validate, build --split-platforms, validate each zip).
numpy is never bundled: Blender ships its own and a second copy breaks it. Wheels are cached in
.cache/wheels (git-ignored), so a rebuild needs no network.
"""
import argparse
import importlib.util
import json
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

from packaging.tags import compatible_tags, cpython_tags
from packaging.utils import parse_wheel_filename

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_DIR = ROOT / "exclone_addon"
MANIFEST = ROOT / "blender_manifest.toml"
WHEEL_CACHE = ROOT / ".cache" / "wheels"
# Blender's own numpy is used; these are the compiled dependencies it does not ship.
BUNDLED_PACKAGES = ("scipy", "opencv-contrib-python-headless")
# Packages the add-on imports only if present, with what it does without them; bundled for every
# platform and Python that has a wheel (pinned in the requirements files like the others).
# threadpoolctl is pure Python: one wheel serves all.
OPTIONAL_PACKAGES = {
    "cholespy": "the transfer factorises with SciPy's SuperLU instead (slower on large meshes)",
    "threadpoolctl": "the add-on leaves the BLAS thread count as it finds it",
}
# (python version, requirements file with its pins), oldest first: a stable-ABI wheel of an older
# Python also serves the newer one.
PYTHONS = (("3.11", ROOT / "requirements.txt"), ("3.13", ROOT / "requirements-py313.txt"))
# pip --platform tags per Blender platform, best first; pip adds the older macOS versions itself.
# macOS 13 is the oldest the OpenCV wheels support (scipy's need 12 on arm64, 10.14 on x64).
PIP_PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64"] + [f"manylinux_2_{v}_x86_64" for v in range(27, 16, -1)]
                 + ["manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_13_0_arm64"],
    "macos-x64": ["macosx_13_0_x86_64"],
}
MODELS = ("face_detection_short_range.tflite", "face_landmark.tflite", "iris_landmark.tflite")
MODELS_LICENCE = "LICENSE-mediapipe-Apache-2.0.txt"
STAGE_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "tests", ".*")
# The project's pip.conf lists file:// indexes that lack most projects; pip warns for each.
PIP_NOISE = "is ignored: it is neither a file nor a directory"


class BuildError(Exception):
    pass


class NoWheelError(BuildError):
    """The package index has no wheel of a requirement for that Python and platform."""


def bpy_scripts_dir():
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise BuildError("the bpy module is not installed in this Python; run `bash scripts/setup.sh` "
                         "and use .venv/bin/python")
    found = sorted(Path(spec.submodule_search_locations[0]).glob("*/scripts"))
    if not found:
        raise BuildError(f"no Blender scripts directory inside {spec.submodule_search_locations[0]}")
    return found[-1]


def read_pins(requirements):
    pins = {}
    for line in requirements.read_text().splitlines():
        match = re.fullmatch(r"\s*([A-Za-z0-9_.-]+)==([^\s#;]+).*", line)
        if match:
            pins[match[1].lower()] = match[2]
    missing = [name for name in (*BUNDLED_PACKAGES, *OPTIONAL_PACKAGES) if name not in pins]
    if missing:
        raise BuildError(f"{requirements.name} has no '==' pin for {', '.join(missing)}")
    return pins


def wheel_serves_python(wheel_name, python):
    """True when a wheel chosen for an older CPython also runs on `python`: stable ABI (abi3) or
    pure Python (py3-none-any)."""
    wheel_tags = parse_wheel_filename(wheel_name)[3]
    version = tuple(map(int, python.split(".")))
    platforms = [t.platform for t in wheel_tags]
    python_tags = set(cpython_tags(version, platforms=platforms)) | set(compatible_tags(version, platforms=platforms))
    return bool(wheel_tags & python_tags)


def pip_download(requirements, python, platform):
    """Download wheels into the cache; returns {requirement: wheel file name}."""
    command = [sys.executable, "-m", "pip", "download", "--disable-pip-version-check", "--no-deps",
               "--only-binary=:all:", "--python-version", python, "--dest", str(WHEEL_CACHE)]
    for tag in PIP_PLATFORMS[platform]:
        command += ["--platform", tag]
    result = subprocess.run(command + requirements, capture_output=True, text=True)
    output = "\n".join(line for line in (result.stdout + result.stderr).splitlines() if PIP_NOISE not in line)
    if result.returncode != 0:
        failure = NoWheelError if "No matching distribution found" in output else BuildError
        raise failure(f"pip could not download {' '.join(requirements)} for Python {python} on {platform}:\n"
                         f"{output}")
    saved = re.findall(r"(?:Saved|File was already downloaded) (\S+\.whl)", output)
    by_project = {Path(path).name.split("-")[0].lower().replace("_", "-"): Path(path).name for path in saved}
    found = {}
    for requirement in requirements:
        name = requirement.split("==")[0]
        if name not in by_project:
            raise BuildError(f"pip reported no wheel for {requirement} ({python}, {platform}):\n{output}")
        found[requirement] = by_project[name]
    return found


def collect_wheels(platforms):
    """Wheel file names (in the cache) to bundle for these Blender platforms."""
    WHEEL_CACHE.mkdir(parents=True, exist_ok=True)
    index_path = WHEEL_CACHE / "exclone-index.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else {}
    wheels = []
    for platform in platforms:
        chosen = {}  # package -> wheel file name, for this platform
        for python, requirements_file in PYTHONS:
            pins = read_pins(requirements_file)
            wanted = []
            for name in (*BUNDLED_PACKAGES, *OPTIONAL_PACKAGES):
                if name in chosen and wheel_serves_python(chosen[name], python):
                    # Blender keeps one wheel per project (the newest), so a second wheel that
                    # also runs on every Python would only replace this one.
                    print(f"  {platform}: {chosen[name]} also serves Python {python}; "
                          f"not adding {name}=={pins[name]}")
                    continue
                wanted.append(f"{name}=={pins[name]}")
            download_missing(wanted, python, platform, index)
            index_path.write_text(json.dumps(index, indent=1, sort_keys=True))
            for requirement in wanted:
                wheel = index.get(f"{requirement} {python} {platform}")
                if wheel is not None:    # None: an optional package without a wheel here
                    chosen[requirement.split("==")[0]] = wheel
                    wheels.append(wheel)
    if any(wheel.lower().startswith("numpy-") for wheel in wheels):
        raise BuildError("refusing to bundle numpy: Blender ships its own")
    return sorted(set(wheels))


def download_missing(requirements, python, platform, index):
    """Download the requirements not in the cache and record their wheels in `index`. The
    required ones go in one pip call; each optional one alone, so that one without a wheel for
    this Python and platform is reported and left out instead of failing the build."""
    missing = [r for r in requirements if not (WHEEL_CACHE / index.get(f"{r} {python} {platform}", "-")).is_file()]
    required = [r for r in missing if r.split("==")[0] not in OPTIONAL_PACKAGES]
    batches = ([required] if required else []) + [[r] for r in missing if r not in required]
    for batch in batches:
        print(f"  downloading {' '.join(batch)} for Python {python}, {platform}")
        try:
            found = pip_download(batch, python, platform)
        except NoWheelError:
            name = batch[0].split("==")[0]
            if name not in OPTIONAL_PACKAGES:
                raise
            print(f"  {platform}: no {batch[0]} wheel for Python {python}; without it "
                  f"{OPTIONAL_PACKAGES[name]}")
            continue
        for requirement, wheel in found.items():
            index[f"{requirement} {python} {platform}"] = wheel


def staged_manifest_text(platforms, wheels):
    text = MANIFEST.read_text()
    platforms_line = re.compile(r"^platforms = \[.*\]$", re.MULTILINE)
    if len(platforms_line.findall(text)) != 1:
        raise BuildError(f"{MANIFEST.name} needs exactly one single-line top-level 'platforms = [...]'")
    if re.search(r"^wheels\s*=", text, re.MULTILINE):
        raise BuildError(f"{MANIFEST.name} must not list wheels; this script adds them")
    listing = ",\n".join(f'  "./wheels/{wheel}"' for wheel in wheels)
    generated = (f"platforms = {json.dumps(list(platforms))}\n"
                 f"# Added by scripts/build_extension.py.\nwheels = [\n{listing},\n]")
    text = platforms_line.sub(lambda _: generated, text)
    tomllib.loads(text)  # fail here, not inside the CLI, if the edit broke the TOML
    return text


def stage(stage_dir, platforms, wheels):
    missing = [name for name in (*MODELS, MODELS_LICENCE) if not (PACKAGE_DIR / "models" / name).is_file()]
    if missing:
        raise BuildError(f"missing in {PACKAGE_DIR / 'models'}: {', '.join(missing)}; "
                         "run `bash scripts/setup.sh`, which extracts the face models from the mediapipe wheel")
    if not (PACKAGE_DIR / "__init__.py").is_file():
        raise BuildError(f"{PACKAGE_DIR / '__init__.py'} is missing: exclone_addon is not an add-on yet")
    if stage_dir.exists():
        shutil.rmtree(stage_dir)
    shutil.copytree(PACKAGE_DIR, stage_dir, ignore=STAGE_IGNORE)
    (stage_dir / "blender_manifest.toml").write_text(staged_manifest_text(platforms, wheels))
    (stage_dir / "wheels").mkdir()
    for wheel in wheels:
        shutil.copy2(WHEEL_CACHE / wheel, stage_dir / "wheels" / wheel)


def run_cli(cli, *args):
    result = subprocess.run([sys.executable, str(cli), *args], capture_output=True, text=True)
    if result.returncode != 0:
        raise BuildError(f"blender_ext {args[0]} failed:\n{result.stdout}{result.stderr}")
    return result.stdout


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--platforms", default=",".join(PIP_PLATFORMS),
                        help="comma-separated Blender platforms (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=ROOT / "dist", help="directory for the zips (default: dist/)")
    parser.add_argument("--stage-dir", type=Path, default=ROOT / "build" / "exclone",
                        help="staging directory, emptied first (default: build/exclone/)")
    args = parser.parse_args(argv)
    platforms = [p.strip() for p in args.platforms.split(",") if p.strip()]
    unknown = [p for p in platforms if p not in PIP_PLATFORMS]
    if unknown or not platforms:
        parser.error(f"unknown platform(s) {', '.join(unknown) or '(none)'}; choose from {', '.join(PIP_PLATFORMS)}")

    try:
        scripts = bpy_scripts_dir()
        cli = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
        valid_tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
        manifest = tomllib.loads(MANIFEST.read_text())
        print(f"collecting wheels for {', '.join(platforms)}")
        wheels = collect_wheels(platforms)
        stage_dir = args.stage_dir.resolve()
        stage(stage_dir, platforms, wheels)
        run_cli(cli, "validate", "--valid-tags", str(valid_tags), str(stage_dir))
        out = args.out.resolve()
        out.mkdir(parents=True, exist_ok=True)
        zips = [out / f"{manifest['id']}-{manifest['version']}-{p.replace('-', '_')}.zip" for p in platforms]
        for old in zips:
            old.unlink(missing_ok=True)
        run_cli(cli, "build", "--source-dir", str(stage_dir), "--output-dir", str(out), "--split-platforms",
                "--valid-tags", str(valid_tags))
        for platform, zip_path in zip(platforms, zips):
            if not zip_path.is_file():
                raise BuildError(f"the CLI did not produce {zip_path}")
            run_cli(cli, "validate", "--valid-tags", str(valid_tags), str(zip_path))
    except BuildError as error:
        print(f"build_extension: error: {error}", file=sys.stderr)
        return 1
    for platform, zip_path in zip(platforms, zips):
        print(f"{platform:12} {zip_path.stat().st_size / 1e6:7.1f} MB  {zip_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
