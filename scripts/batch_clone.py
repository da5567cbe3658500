"""Clone facial expressions onto a head from the command line.

    python scripts/batch_clone.py [--source S] [--target T] [--out OUT.blend] [--export-dir DIR]
        [--report R.json] [--landmarks L.json] [--shapes NAME,NAME...] [--preview P.png]
        [--no-preview]
    python scripts/batch_clone.py --target T1 --target T2|FOLDER ... [--out-dir DIR] [--jobs N]
    blender -b --python scripts/batch_clone.py -- ARGS

With no arguments: the bundled ICT-FaceKit ARKit library onto the bundled demo head, written to
out/demo_head_exclone.blend, .json and .png (--no-preview: no .png, and no render, which takes
a few seconds per target). The .json report holds, besides timings and fit quality, each
expression's measures (core.expression_measures: lid and lip gaps, stretch, flips, motion outside
the face) and their summary, which the console shows on its "measures:" line.

Input files are only read (see exclone_addon/blender/files.py). Every output path is checked
before any work; the outputs are written under temporary names and moved into place together at
the end, so a run that fails (bad input, a full disk) leaves no half-written file.

Several targets (--target given more than once, or a folder of meshes) make a batch: each target
runs in its own process, --jobs N at a time, writing <out-dir>/<target>_exclone.blend, .json and
.png, plus one summary report (--report, default <out-dir>/batch_report.json). A bad target is
reported and skipped; the exit code is non-zero if any target failed.
"""
import json
import os
import platform
import re
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import bpy

try:
    import scipy  # noqa: F401  (Blender ships numpy but not scipy)
except ImportError:
    sys.exit("batch_clone: error: scipy is not available in this Python; inside Blender, install and "
             "enable the ExClone extension first (it bundles scipy), or run with .venv/bin/python")

SCRIPT = Path(__file__).resolve()
sys.path[:0] = [str(SCRIPT.parent.parent), str(SCRIPT.parent)]  # exclone_addon, exclone_cli
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from exclone_cli import (Outputs, Parser, check_folder_writable, check_output_writable,  # noqa: E402
                         number, run_main)
from exclone_addon.blender import character, files, mesh_io, preview, workflow  # noqa: E402
from exclone_addon.core import data, reports  # noqa: E402
from exclone_addon.core.cloning import CloneSettings, clone_expressions  # noqa: E402
from exclone_addon.core.errors import ExCloneError  # noqa: E402
from exclone_addon.core.expression_measures import measure_clone, summary  # noqa: E402
from exclone_addon.core.landmarks import checked_pairs  # noqa: E402
from exclone_addon.core.mesh import PolyMesh, write_obj  # noqa: E402

PROG = "batch_clone"
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _parser():
    parser = Parser(
        prog="batch_clone.py",
        description="Clone facial expressions onto a head mesh and save them as shape keys.")
    parser.add_argument("--source", metavar="S",
                        help="expressions: a .blend[:Object], .fbx or .glb mesh with shape keys, "
                             "or a folder with neutral.obj + one OBJ per expression "
                             "(default: the bundled ICT-FaceKit ARKit library)")
    parser.add_argument("--target", metavar="T", action="append",
                        help="head to receive them: .blend[:Object], .obj, .fbx or .glb "
                             "(default: the bundled demo head). Give it several times, or a "
                             "folder of such files, for a batch: one output per target in "
                             "--out-dir and one summary report")
    parser.add_argument("--out", metavar="OUT.blend",
                        help="result .blend (default: out/<target name>_exclone.blend)")
    parser.add_argument("--out-dir", metavar="DIR",
                        help="batch only: where each target's .blend, .json and .png go "
                             "(default: out)")
    parser.add_argument("--jobs", metavar="N", type=number(int, at_least=1), default=1,
                        help="batch only: targets processed at once, each in its own process "
                             "(default: 1)")
    parser.add_argument("--export-dir", metavar="DIR",
                        help="also write neutral.obj and one OBJ per new shape key, in the "
                             "target's own coordinates and vertex order")
    parser.add_argument("--report", metavar="R.json", help="JSON report (default: OUT with .json)")
    parser.add_argument("--landmarks", metavar="L.json",
                        help='{"source": [ids], "target": [ids]}: 0-based vertex ids to use '
                             "instead of the automatic landmarks")
    parser.add_argument("--shapes", metavar="NAME,NAME...",
                        help="clone only these expressions")
    parser.add_argument("--preview", metavar="P.png",
                        help="contact sheet of rendered expressions (default: OUT with .png)")
    parser.add_argument("--no-preview", action="store_true",
                        help="no contact sheet (saves its render, a few seconds per target)")
    return parser


def parse_args(argv):
    args = _parser().parse_args(argv)
    if args.preview and args.no_preview:
        raise ExCloneError("--preview names the contact sheet that --no-preview skips; give one "
                           "of them")
    targets = args.target or []
    args.batch = len(targets) > 1 or any(files.split_spec(t)[0].is_dir() for t in targets)
    if not args.batch:
        args.target = targets[0] if targets else None
        for option, given in (("--out-dir", args.out_dir is not None), ("--jobs", args.jobs != 1)):
            if given:
                raise ExCloneError(f"{option} is for several targets (give --target more than "
                                   "once, or a folder)")
    else:
        for option, value in (("--out", args.out), ("--preview", args.preview)):
            if value:
                raise ExCloneError(f"{option} names one file; with several targets each one's "
                                   "outputs go to --out-dir")
    return args


# -- one target ----------------------------------------------------------------------------------

@dataclass
class OutputPaths:
    blend: Path
    report: Path
    preview: Path         # None: --no-preview
    export_dir: Path = None

    def files(self):
        """The output files (not the export folder's)."""
        return [path for path in (self.blend, self.report, self.preview) if path is not None]


def output_paths(args):
    """Where one target's outputs go; ExCloneError at once if any of them cannot be written."""
    target_file = data.DEMO_HEAD_FILE if args.target is None else files.split_spec(args.target)[0]
    out = Path(args.out) if args.out else Path("out") / f"{target_file.stem}_exclone.blend"
    if out.suffix.lower() != ".blend":
        raise ExCloneError(f"--out must name a .blend file, got {out}")
    preview = None if args.no_preview else \
        Path(args.preview) if args.preview else out.with_suffix(".png")
    paths = OutputPaths(out, Path(args.report) if args.report else out.with_suffix(".json"),
                        preview, Path(args.export_dir) if args.export_dir else None)
    if preview is not None and preview.suffix.lower() != ".png":
        raise ExCloneError(f"--preview must name a .png file, got {preview}")
    for path in paths.files():
        check_output_writable(path)
    if paths.export_dir is not None:
        check_folder_writable(paths.export_dir)
    return paths


def source_inputs(spec):
    """The files a --source spec reads (none of them may be overwritten)."""
    if spec is None:
        return [data.LIBRARY_FILE]
    path = files.split_spec(spec)[0]
    return [path, *sorted(path.glob("*.obj"))] if path.is_dir() else [path]


def selected_shapes(source, shapes):
    """The source restricted to the --shapes list (None: all of it)."""
    if shapes is None:
        return source
    wanted = list(dict.fromkeys(name.strip() for name in shapes.split(",") if name.strip()))
    if not wanted:
        raise ExCloneError("--shapes names no expression")
    unknown = [name for name in wanted if name not in source.names]
    if unknown:
        raise ExCloneError(f"unknown expression(s) {', '.join(unknown)}; available: "
                           f"{', '.join(source.names[:6])}, ... ({len(source.names)} in all)")
    return source.subset(wanted)


def read_landmarks(path, n_source, n_target):
    """{"source": ids, "target": ids} from a JSON file, checked against both meshes by
    core.landmarks.checked_pairs; errors name the file."""
    if not path.exists():
        raise ExCloneError(f"landmarks file not found: {path}")
    try:
        pairs = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ExCloneError(f"landmarks file {path} is not valid JSON ({exc})") from exc
    try:
        source, target = checked_pairs(pairs, n_source, n_target)
    except ExCloneError as exc:
        raise ExCloneError(f"landmarks file {path}: {str(exc).removeprefix('landmarks: ')}") \
            from None
    return {"source": source, "target": target}


def _file_stem(name):
    return re.sub(r"[^\w.-]", "_", name)


def export_paths(directory, names):
    """neutral.obj plus <name>.obj per shape key; refuses names that would share a file."""
    paths = {"neutral": Path(directory) / "neutral.obj"}
    for name in names:
        path = Path(directory) / f"{_file_stem(name)}.obj"
        if path in paths.values():
            raise ExCloneError(f"cannot export shape key '{name}': its file name {path.name} "
                               "is already used by another shape key or the neutral")
        paths[name] = path
    return paths


def export_shapes(outputs, directory, neutral, names, deltas):
    """Write neutral.obj and neutral + delta per name as OBJs (neutral's coordinates and order)
    through `outputs` (exclone_cli.Outputs); returns {name: final path}."""
    paths = export_paths(directory, names)
    outputs.write(paths["neutral"], lambda path: write_obj(path, neutral,
                                                             header="ExClone: neutral"))
    for name, delta in zip(names, deltas):
        shape = PolyMesh(neutral.vertices + delta, neutral.loop_totals, neutral.loop_vertices)
        outputs.write(paths[name], lambda path: write_obj(path, shape,
                                                            header=f"ExClone: shape key {name}"))
    return paths


def refuse_overwriting_inputs(outputs, inputs):
    resolved_inputs = {Path(p).resolve() for p in inputs}
    seen = set()
    for path in outputs:
        resolved = Path(path).resolve()
        if resolved in resolved_inputs:
            raise ExCloneError(f"refusing to overwrite the input file {path}; choose another "
                               "output path")
        if resolved in seen:
            raise ExCloneError(f"two outputs would be written to {path}")
        if resolved.is_dir():
            raise ExCloneError(f"output {path} is a folder")
        seen.add(resolved)


def _print_progress():
    last = [None]

    def progress(fraction, message):
        if message != last[0]:
            print(f"  {fraction:4.0%} {message}", flush=True)
            last[0] = message
    return progress


def _json_value(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _write_json(outputs, path, content):
    text = json.dumps(content, indent=2, default=_json_value) + "\n"
    outputs.write(path, lambda temporary: temporary.write_text(text, encoding="utf-8"))


def _write_png(path, image):
    if not cv2.imwrite(str(path), image):
        raise OSError("OpenCV could not write the image")


@dataclass
class Inputs:
    source: object        # core.library.ExpressionLibrary
    target: files.Target
    landmarks: dict       # {"source": ids, "target": ids} or None (automatic)
    read: list            # every input file read (none may be overwritten)


def read_inputs(args, paths, timings):
    """Source, target and landmarks, each checked; ExCloneError before any cloning."""
    clock = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    source = selected_shapes(files.load_source(args.source), args.shapes)
    timings["read_source"] = time.perf_counter() - clock
    clock = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)  # the saved file holds only the target
    target = files.load_target(args.target)
    timings["read_target"] = time.perf_counter() - clock
    inputs = source_inputs(args.source) + [files.split_spec(args.target)[0] if args.target
                                           else data.DEMO_HEAD_FILE]
    landmarks = None
    if args.landmarks:
        landmarks = read_landmarks(Path(args.landmarks), len(source.mesh.vertices),
                                   len(target.mesh.vertices))
        inputs.append(Path(args.landmarks))
    outputs = paths.files()
    if paths.export_dir is not None:
        outputs += export_paths(paths.export_dir, source.names).values()
    refuse_overwriting_inputs(outputs, inputs)
    return Inputs(source, target, landmarks, inputs)


def write_outputs(outputs, paths, target, result, timings):
    """The target's new shape keys, saved in a .blend, exported as OBJs and rendered (unless
    --no-preview); returns (added, replaced, skipped, exported paths or None, preview engine or
    None)."""
    clock = time.perf_counter()
    added, replaced, skipped = mesh_io.write_shape_keys(target.obj, result.names, result.deltas)
    timings["write_shape_keys"] = time.perf_counter() - clock
    clock = time.perf_counter()
    outputs.write(paths.blend, lambda path: files.save_copy(path, holds=target.obj.name))
    timings["save_blend"] = time.perf_counter() - clock
    exported = None
    if paths.export_dir is not None:
        clock = time.perf_counter()
        rows = [result.names.index(name) for name in added]
        exported = export_shapes(outputs, paths.export_dir, target.mesh, added,
                                 result.deltas[rows])
        timings["export_obj"] = time.perf_counter() - clock
    engine = None
    if paths.preview is not None:
        clock = time.perf_counter()
        sheet, engine = preview.contact_sheet(target.obj, target.mesh.vertices[
            target.face.head.vertex_ids], added)          # framing the head
        outputs.write(paths.preview, lambda path: _write_png(path, sheet))
        timings["preview"] = time.perf_counter() - clock
    return added, replaced, skipped, exported, engine


def build_report(args, paths, inputs, result, written, timings):
    source, target = inputs.source, inputs.target
    added, _, skipped, exported, engine = written
    return {
        "inputs": {"source": source.description, "target": target.description,
                   "face": target.face.description(),
                   "landmarks": args.landmarks, "shapes": args.shapes},
        "counts": {"source_vertices": len(source.mesh.vertices),
                   "source_triangles": len(source.mesh.triangles()),
                   "target_vertices": len(target.mesh.vertices),
                   "target_triangles": len(target.mesh.triangles()),
                   "expressions": len(result.names), "shape_keys_added": len(added),
                   "shape_keys_skipped": len(skipped)},
        "timings": timings,
        "quality": result.quality,
        "landmarks": {"source": result.source_landmarks, "target": result.target_landmarks,
                      "names": list(result.landmark_names),
                      "automatic": inputs.landmarks is None},
        "outputs": {"blend": str(paths.blend), "report": str(paths.report),
                    "preview": str(paths.preview) if paths.preview else None,
                    "preview_engine": engine,
                    "export_dir": args.export_dir,
                    "exported_files": len(exported) if exported else 0,
                    "target_object": target.obj.name,
                    "shape_keys_added": added, "shape_keys_skipped_existing": skipped},
        "versions": {"blender": bpy.app.version_string, "numpy": np.__version__,
                     "python": platform.python_version()},
    }


def run(args):
    """One target, everything the CLI does; returns the report (a dict). ExCloneError on bad
    input or an output that cannot be written, and then no output is left behind."""
    started = time.perf_counter()
    paths = output_paths(args)
    timings = {}
    inputs = read_inputs(args, paths, timings)
    clock = time.perf_counter()
    # only the head of the face's object is solved, in world space (files.load_target)
    target = inputs.target
    face, landmarks = workflow.in_head(target.face, character.parts([target.obj])[0],
                                       inputs.landmarks)
    target.face = face
    result = clone_expressions(inputs.source.mesh, inputs.source.deltas, inputs.source.names,
                               face.head.mesh, landmarks=landmarks,
                               source_landmarks=inputs.source.automatic_landmarks,
                               settings=CloneSettings(), progress=_print_progress(),
                               face_guide=face.guide, fixed_vertices=face.head.fixed)
    timings.update({f"clone_{phase}": seconds for phase, seconds in result.timings.items()})
    timings["clone_total"] = time.perf_counter() - clock
    clock = time.perf_counter()
    measures = measure_clone(face.head.mesh, result)
    # from here on, the face's object's own numbering and coordinates
    result.deltas = workflow.face_object_deltas(target.obj, face, result.deltas)
    result.target_landmarks = face.head.own_ids(result.target_landmarks)
    timings["measures"] = time.perf_counter() - clock
    with Outputs() as outputs:
        written = write_outputs(outputs, paths, inputs.target, result, timings)
        timings["total"] = time.perf_counter() - started
        report = build_report(args, paths, inputs, result, written, timings)
        report["measures"] = {"summary": summary(measures), "expressions": measures}
        _write_json(outputs, paths.report, report)
        outputs.commit()
    added, replaced, skipped, exported, _ = written
    print(f"blend:   {paths.blend}\nreport:  {paths.report}"
          + (f"\npreview: {paths.preview}" if paths.preview else "")
          + (f"\nexport:  {paths.export_dir} ({len(exported)} OBJs)" if exported else ""))
    print("measures: " + (reports.measures_clause(report["measures"]["summary"]) or "none"))
    rendered = f", preview {timings['preview']:.1f} s" if paths.preview else ""
    print(f"{target.face.description()}\n{target.obj.name}: "
          + reports.summary(added, replaced, skipped, timings["total"], result.quality)
          + f" (cloning {timings['clone_total']:.1f} s{rendered})")
    return report


# -- several targets, each in its own process ----------------------------------------------------

def batch_targets(specs):
    """The --target values with each folder replaced by its mesh files (sorted by name)."""
    targets = []
    for spec in specs:
        path, _ = files.split_spec(spec)
        if not path.is_dir():
            targets.append(spec)
            continue
        found = sorted(p for p in path.iterdir()
                       if p.is_file() and p.suffix.lower() in files.TARGET_SUFFIXES)
        if not found:
            raise ExCloneError(f"target folder {path} holds no .blend, .obj, .fbx, .glb or "
                               ".gltf file")
        targets += [str(p) for p in found]
    return targets


def output_stems(targets):
    """One output name per target: the file's stem (and object), made unique with -2, -3..."""
    stems, seen = [], {}
    for spec in targets:
        path, name = files.split_spec(spec)
        stem = _file_stem(path.stem + (f"_{name}" if name else ""))
        seen[stem] = seen.get(stem, 0) + 1
        stems.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return stems


def _child_command():
    """How to run this script on one target in a new process: the bpy module's Python or the
    Blender executable."""
    if bpy.app.binary_path:
        return [bpy.app.binary_path, "-b", "--python", str(SCRIPT), "--"]
    return [sys.executable, str(SCRIPT)]


def _run_target(command, spec, out, shared_args, env, export_dir):
    """This script on one target; returns its summary entry (never raises for a failed target)."""
    arguments = ["--target", spec, "--out", str(out)] + shared_args
    if export_dir is not None:
        arguments += ["--export-dir", str(export_dir)]
    clock = time.perf_counter()
    done = subprocess.run(command + arguments, capture_output=True, text=True, env=env)
    entry = {"target": spec, "seconds": round(time.perf_counter() - clock, 2)}
    if done.returncode != 0:
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        error = lines[-1].removeprefix(f"{PROG}: error: ") if lines else \
            f"exited with code {done.returncode}"
        entry.update(status="failed", error=error)
        return entry
    report = json.loads(out.with_suffix(".json").read_text(encoding="utf-8"))
    entry.update(status="ok", blend=str(out), report=str(out.with_suffix(".json")),
                 preview=report["outputs"]["preview"],
                 shape_keys_added=report["counts"]["shape_keys_added"],
                 fit_error_rel=report["quality"].get("registration_mean_distance_rel"))
    return entry


def _batch_environment(jobs):
    env = dict(os.environ)
    if jobs > 1:  # the processes share the cores: one BLAS thread pool each, not one per core
        for name in BLAS_THREADS:
            env.setdefault(name, str(max(1, (os.cpu_count() or 1) // jobs)))
    return env


def _batch_paths(args, targets):
    """(out_dir, summary path), checked before any target runs."""
    out_dir = Path(args.out_dir or "out")
    summary_path = Path(args.report) if args.report else out_dir / "batch_report.json"
    if summary_path.suffix.lower() != ".json":
        raise ExCloneError(f"--report must name a .json file, got {summary_path}")
    refuse_overwriting_inputs([summary_path], [files.split_spec(t)[0] for t in targets
                                               if files.split_spec(t)[0].exists()])
    check_folder_writable(out_dir)
    check_output_writable(summary_path)
    if args.export_dir:
        check_folder_writable(args.export_dir)
    return out_dir, summary_path


def _run_targets(args, targets, out_dir):
    """Every target through this script in its own process, --jobs at a time (one bad or
    crashing target cannot stop the others); their summary entries, in target order."""
    shared = []
    for option, value in (("--source", args.source), ("--landmarks", args.landmarks),
                          ("--shapes", args.shapes)):
        if value is not None:
            shared += [option, value]
    if args.no_preview:
        shared.append("--no-preview")
    jobs, command, stems = min(args.jobs, len(targets)), _child_command(), output_stems(targets)
    env = _batch_environment(jobs)
    print(f"batch: {len(targets)} target(s), {jobs} at a time", flush=True)

    def one(index):
        export = Path(args.export_dir) / stems[index] if args.export_dir else None
        entry = _run_target(command, targets[index], out_dir / f"{stems[index]}_exclone.blend",
                            shared, env, export)
        outcome = (f"{entry['shape_keys_added']} shape keys added" if entry["status"] == "ok"
                   else f"FAILED: {entry['error']}")
        print(f"[{index + 1}/{len(targets)}] {targets[index]}: {outcome} "
              f"({entry['seconds']:.1f} s)", flush=True)
        return entry

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(one, range(len(targets)))), jobs


def run_batch(args):
    """Every target (_run_targets), then the summary report; returns the summary. ExCloneError
    if any target failed, after the others were written."""
    started = time.perf_counter()
    targets = batch_targets(args.target)
    out_dir, summary_path = _batch_paths(args, targets)
    entries, jobs = _run_targets(args, targets, out_dir)
    failed = [entry for entry in entries if entry["status"] != "ok"]
    summary = {"targets": entries, "succeeded": len(entries) - len(failed), "failed": len(failed),
               "jobs": jobs, "seconds": round(time.perf_counter() - started, 2),
               "arguments": {"source": args.source, "landmarks": args.landmarks,
                             "shapes": args.shapes, "no_preview": args.no_preview,
                             "out_dir": str(out_dir),
                             "export_dir": args.export_dir}}
    with Outputs() as outputs:
        _write_json(outputs, summary_path, summary)
        outputs.commit()
    print(f"summary: {summary_path} ({summary['succeeded']} ok, {len(failed)} failed, "
          f"{summary['seconds']:.1f} s)")
    if failed:
        raise ExCloneError(f"{len(failed)} of {len(entries)} targets failed (first: "
                           f"{failed[0]['target']}: {failed[0]['error']}); the others were "
                           f"written; summary: {summary_path}")
    return summary


def main(argv):
    """Run the CLI on argv (the arguments after the script); returns the exit code."""
    def work():
        args = parse_args(argv)
        if args.batch:
            run_batch(args)
        else:
            run(args)

    return run_main(PROG, work)


def script_arguments():
    if "--" in sys.argv:
        return sys.argv[sys.argv.index("--") + 1:]
    # Inside the Blender executable, sys.argv holds Blender's own options.
    return [] if bpy.app.binary_path else sys.argv[1:]


if __name__ == "__main__":
    sys.exit(main(script_arguments()))
