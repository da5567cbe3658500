"""flamenco/exclone_batch.js, the Flamenco job type: its compile step run under node with the
documented job-compiler globals (blender_tests/helpers/flamenco_compile.js) gives one task per
target running scripts/batch_clone.py in Blender, and a summary task that depends on all of them.
"""
import json
import shutil
import subprocess

import pytest

from blender_tests.helpers.paths import REPO_ROOT

JOB_SCRIPT = REPO_ROOT / "flamenco" / "exclone_batch.js"
HARNESS = REPO_ROOT / "blender_tests" / "helpers" / "flamenco_compile.js"
# the same targets and names as test_batch_clone.test_output_names_are_unique_per_target, which
# checks that batch_clone.output_stems gives these names too
TARGETS = ["/farm/heads/anna.obj", "/farm/more/anna.obj", "/farm/chars/Bob v2.blend:Head",
           "/farm/chars/élodie.glb", "/farm/scan.final.fbx"]
STEMS = ["anna", "anna-2", "Bob_v2_Head", "_lodie", "scan.final"]
SCRIPT = "{exclone}/scripts/batch_clone.py"


@pytest.fixture(scope="module")
def node():
    found = shutil.which("node")
    if found is None:
        pytest.skip("node (Node.js) is not installed: the Flamenco job type's compile step "
                    "cannot be run")
    return found


def compiled(node, tmp_path, **settings):
    path = tmp_path / "settings.json"
    path.write_text(json.dumps(settings), encoding="utf-8")
    done = subprocess.run([node, str(HARNESS), str(JOB_SCRIPT), str(path)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode in (0, 2), done.stderr
    return json.loads(done.stdout)


def blender_command(args):
    return {"name": "blender-render",
            "parameters": {"exe": "{blender}", "exeArgs": "{blenderArgs}", "argsBefore": [],
                           "blendfile": "", "args": ["--python", SCRIPT, "--", *args]}}


def test_one_task_per_target_and_a_summary_after_all_of_them(node, tmp_path):
    result = compiled(node, tmp_path, targets=" ; ".join(TARGETS) + ";", out_dir="/farm/out",
                      format="glb", source="/farm/ict/source.blend", shapes="jawOpen,eyeBlink_L",
                      preview=False, overwrite=False, script=SCRIPT)
    tasks = result["tasks"]
    assert [task["name"] for task in tasks] == [f"clone-{stem}" for stem in STEMS] + ["summary"]
    assert {task["type"] for task in tasks} == {"blender"}
    shared = ["--source", "/farm/ict/source.blend", "--shapes", "jawOpen,eyeBlink_L",
              "--no-preview", "--resume"]
    for task, target, stem in zip(tasks, TARGETS, STEMS):
        assert task["commands"] == [blender_command(
            ["--target", target, "--out", f"/farm/out/{stem}_exclone.glb", *shared])]
        assert task["dependencies"] == []
    listed = [arg for target in TARGETS for arg in ("--target", target)]
    assert tasks[-1]["commands"] == [blender_command(
        ["--summary-only", "--out-dir", "/farm/out", "--format", "glb", *listed])]
    assert tasks[-1]["dependencies"] == [f"clone-{stem}" for stem in STEMS]


def test_defaults_and_options(node, tmp_path):
    """Without source or shapes: the bundled library, every expression, a .blend each; a
    contact sheet when asked; --overwrite instead of --resume when asked; the script's default
    path (the Manager's {exclone} variable) if the setting is missing."""
    result = compiled(node, tmp_path, targets="/farm/a.obj", out_dir="/farm/out", source="",
                      shapes="", preview=True, overwrite=True)
    first, summary = result["tasks"]
    assert first["commands"] == [blender_command(
        ["--target", "/farm/a.obj", "--out", "/farm/out/a_exclone.blend", "--overwrite"])]
    assert summary["dependencies"] == ["clone-a"]
    assert summary["commands"][0]["parameters"]["args"][3:] == [
        "--summary-only", "--out-dir", "/farm/out", "--format", "blend", "--target", "/farm/a.obj"]
    settings = {s["key"]: s for s in result["job_type"]["settings"]}
    assert settings["format"]["choices"] == ["blend", "glb", "fbx"]
    assert settings["targets"]["required"] and settings["out_dir"]["required"]


def test_no_targets_is_a_compile_error(node, tmp_path):
    result = compiled(node, tmp_path, targets=" ; ", out_dir="/farm/out")
    assert result == {"error": "ExClone Batch: no targets; list the target files separated by ';'"}
