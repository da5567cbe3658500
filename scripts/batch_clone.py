"""Clone facial expressions onto a head from the command line.

    python scripts/batch_clone.py [--source S] [--target T] [--out OUT.blend|.glb|.fbx]
        [--export-dir DIR] [--report R.json] [--landmarks L.json] [--shapes NAME,NAME...]
        [--preview P.png] [--no-preview] [--overwrite | --resume]
    python scripts/batch_clone.py --target T1 --target T2|FOLDER ... [--out-dir DIR] [--jobs N]
        [--format blend|glb|fbx] [--overwrite | --resume | --summary-only]
    blender -b --python scripts/batch_clone.py -- ARGS

With no arguments: the bundled ICT-FaceKit ARKit library onto the bundled demo head, written to
out/demo_head_exclone.blend, .json and .png (--no-preview: no .png, and no render, which takes
a few seconds per target). The .json report holds, besides timings and fit quality, each
expression's measures (core.expression_measures: lid and lip gaps, stretch, flips, motion outside
the face) and their summary, which the console shows on its "measures:" line.

--out x.glb or x.fbx writes the target through Blender's own glTF or FBX exporter instead of a
.blend, its shape keys as morph targets (glTF) or blend shapes (FBX) with the same names.
A character's other objects (eyes, brows, lashes, teeth, tongue) get the new keys as Clone gives
them (driven by the face's keys in a .blend); the report's outputs.other_objects says what each got.

Input files are only read (see exclone_addon/blender/files.py). Every output path is checked
before any work; an output that exists is replaced only with --overwrite (--resume: a target
whose report exists is done and skipped). The outputs are written under temporary names and moved
into place together at the end, so a run that fails (bad input, a full disk) leaves no
half-written file; the report is moved last, so a report on disk means a finished target.

On Linux, when the source is plain files (the bundled library, a folder of OBJs), a forked copy
of the process reads it and, for an OBJ target without --landmarks, finds the face and clones
while the process loads Blender (scripts/clone_worker.py): the same result, sooner.

Several targets (--target given more than once, or a folder of meshes) make a batch: each target
runs in its own process, --jobs N at a time (by default as many as the CPUs and the free memory
allow: plan_jobs), writing <out-dir>/<target>_exclone.blend (or --format), .json and .png, plus
one summary (--report, default <out-dir>/batch_report.json) listing every target as done,
failed (with its message) or skipped (done in an earlier run: --resume), its seconds and
outputs. A failed target does not stop the others; the exit code is non-zero if any failed.
--summary-only writes the summary from the outputs on disk without running anything (the
Flamenco job type's last task: flamenco/exclone_batch.js).
"""
import contextlib
import ctypes
import functools
import json
import os
import platform
import re
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

try:
    import scipy  # noqa: F401  (Blender ships numpy but not scipy)
except ImportError:
    sys.exit("batch_clone: error: scipy is not available in this Python; inside Blender, install and "
             "enable the ExClone extension first (it bundles scipy), or run with .venv/bin/python")

SCRIPT = Path(__file__).resolve()
sys.path[:0] = [str(SCRIPT.parent.parent), str(SCRIPT.parent)]  # exclone_addon, exclone_cli
# The engine (and what parses the arguments) before Blender, which is loaded below
from clone_worker import ONE_PROCESS, CloneProcess, can_fork, cloned, selected_shapes  # noqa: E402
from exclone_cli import (Outputs, Parser, check_folder_writable, check_output_writable,  # noqa: E402
                         number, run_main)
from exclone_addon.blender.plain_files import (RESULT_SUFFIXES, TARGET_SUFFIXES,  # noqa: E402
                                             source_is_plain_files, split_spec)
from exclone_addon.core.errors import ExCloneError  # noqa: E402

PROG = "batch_clone"
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
OUT_SUFFIXES = RESULT_SUFFIXES                # .blend, .glb, .fbx
MIB = 1024 * 1024
# One target's process, for sizing --jobs by free memory. Measured (peak RSS of the bpy-module
# process, 57 expressions, --no-preview, the streamed transfer): 520 MiB onto the 4,244-vertex
# demo head, 875 MiB onto the 66,649-vertex MakeHuman dense head, i.e. ~500 MiB + 5.8 KiB per
# target vertex. Rounded up, the slope doubled (other sources, more expressions): a batch errs
# towards fewer jobs, never towards swapping. Several jobs' targets run without the forked copy
# (clone_worker.ONE_PROCESS), which would add ~100 MiB each.
JOB_BASE_BYTES = 512 * MIB
JOB_BYTES_PER_VERTEX = 12 * 1024
# A target that is not an OBJ is not opened to count its vertices: its file size over this
# many bytes per vertex (a glTF/FBX/.blend holds at least a position, a normal and UVs per
# vertex, ~32 bytes) overestimates the count, the safe side.
FILE_BYTES_PER_VERTEX = 32
MEMORY_MARGIN = 0.8                           # of the memory available now: the rest for others


def _parser():
    parser = Parser(
        prog="batch_clone.py",
        description="Clone facial expressions onto a head mesh and save them as shape keys.")
    parser.add_argument("--source", metavar="S",
                        help="expressions: a .blend[:Object], .fbx or .glb mesh with shape keys "
                             "(a full body too: its keys are taken at the face found on it), "
                             "or a folder with neutral.obj + one OBJ per expression "
                             "(default: the bundled ICT-FaceKit ARKit library)")
    parser.add_argument("--target", metavar="T", action="append",
                        help="head to receive them: .blend[:Object], .obj, .fbx or .glb "
                             "(default: the bundled demo head). Give it several times, or a "
                             "folder of such files, for a batch: one output per target in "
                             "--out-dir and one summary report")
    parser.add_argument("--out", metavar="OUT.blend",
                        help="result: a .blend, or a .glb or .fbx written by Blender's exporter "
                             "with the shape keys as morph targets (default: "
                             "out/<target name>_exclone.blend)")
    parser.add_argument("--out-dir", metavar="DIR",
                        help="batch only: where each target's result, .json and .png go "
                             "(default: out)")
    parser.add_argument("--format", choices=[s.lstrip(".") for s in OUT_SUFFIXES],
                        help="batch only: each target's result file type (default: blend)")
    parser.add_argument("--jobs", metavar="N", type=number(int, at_least=1),
                        help="batch only: targets processed at once, each in its own process "
                             "(default: as many as the CPUs and the free memory allow)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace outputs that exist (without it they are never replaced)")
    parser.add_argument("--resume", action="store_true",
                        help="skip targets that are done (their report exists): continue an "
                             "interrupted batch")
    parser.add_argument("--summary-only", action="store_true",
                        help="batch only: run nothing, write the summary of the outputs on "
                             "disk (the last task of a render-farm job)")
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
    if args.overwrite and args.resume:
        raise ExCloneError("--overwrite replaces what --resume keeps; give one of them")
    targets = args.target or []
    args.batch = len(targets) > 1 or any(split_spec(t)[0].is_dir() for t in targets) \
        or (args.summary_only and bool(targets))
    if not args.batch:
        args.target = targets[0] if targets else None
        for option, given in (("--out-dir", args.out_dir is not None),
                              ("--jobs", args.jobs is not None), ("--format", args.format),
                              ("--summary-only", args.summary_only)):
            if given:
                raise ExCloneError(f"{option} is for several targets (give --target more than "
                                   "once, or a folder)")
    else:
        for option, value in (("--out", args.out), ("--preview", args.preview)):
            if value:
                raise ExCloneError(f"{option} names one file; with several targets each one's "
                                   "outputs go to --out-dir")
    return args


def script_arguments(blender_executable):
    if "--" in sys.argv:
        return sys.argv[sys.argv.index("--") + 1:]
    # Inside the Blender executable, sys.argv holds Blender's own options.
    return [] if blender_executable else sys.argv[1:]


def started_clone_process(argv):
    """A CloneProcess reading the source, started now, when argv asks for one target from a
    source of plain files (the bundled library, a folder of OBJs), and cloning at once without
    --landmarks (they are read beside the target); else None (everything runs in this
    process). Bad arguments are left for main to report."""
    try:
        args = parse_args(argv)
    except ExCloneError:
        return None
    if args.batch or not source_is_plain_files(args.source) or not can_fork():
        return None
    try:
        return CloneProcess(args.source, args.shapes, args.target, guess=args.landmarks is None)
    except OSError:     # no process to be had (a limit on them): all of it in this one
        return None


# The bpy module's Python (Blender's own has loaded bpy before this script): the source is read
# and the clone made in a copy of this process while this one loads Blender.
CLONE_PROCESS = started_clone_process(script_arguments(blender_executable=False)) \
    if __name__ == "__main__" and "bpy" not in sys.modules else None

import bpy  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402
from exclone_addon.blender import (character, character_keys, files, mesh_io, preview,  # noqa: E402
                                     workflow)
from exclone_addon.core import data, reports  # noqa: E402
from exclone_addon.core.expression_measures import summary  # noqa: E402
from exclone_addon.core.landmarks import checked_pairs  # noqa: E402
from exclone_addon.core.mesh import PolyMesh, write_obj  # noqa: E402


# -- one target ----------------------------------------------------------------------------------

@dataclass
class OutputPaths:
    result: Path          # .blend, .glb or .fbx
    report: Path
    preview: Path         # None: --no-preview
    export_dir: Path = None

    def files(self):
        """The output files (not the export folder's)."""
        return [path for path in (self.result, self.report, self.preview) if path is not None]


def output_paths(args):
    """Where one target's outputs go; ExCloneError at once if any of them cannot be written."""
    target_file = data.DEMO_HEAD_FILE if args.target is None else split_spec(args.target)[0]
    out = Path(args.out) if args.out else Path("out") / f"{target_file.stem}_exclone.blend"
    if out.suffix.lower() not in OUT_SUFFIXES:
        raise ExCloneError(f"--out must name a .blend, .glb or .fbx file, got {out}")
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
    path = split_spec(spec)[0]
    return [path, *sorted(path.glob("*.obj"))] if path.is_dir() else [path]


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


def in_source_head(source, landmarks):
    """The landmark pairs with their source ids (the source object's own numbering) in the
    source's (its head region's when it was cut to one, a full body); ExCloneError if one lies
    outside it."""
    inside = source.ids_from_own(landmarks["source"])
    if inside is None:
        raise ExCloneError(f"--landmarks: some source landmarks lie outside the head region of "
                           f"{source.description} where its face was found; place them on the "
                           "face")
    return {"source": inside.tolist(), "target": landmarks["target"]}


def _file_stem(name):
    """name as a portable file name: anything but ASCII letters, digits, '_', '.', '-' as '_'
    (flamenco/exclone_batch.js names a farm's outputs by the same rule)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name)


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


def refuse_replacing(outputs, overwrite):
    """ExCloneError if an output exists and --overwrite was not given (nothing of the user's is
    replaced without being asked)."""
    existing = [Path(path) for path in outputs if Path(path).exists()]
    if existing and not overwrite:
        more = f" (and {len(existing) - 1} more)" if len(existing) > 1 else ""
        raise ExCloneError(f"{existing[0]}{more} exists; give --overwrite to replace it, or "
                           "choose another output")


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


def empty_factory_scene():
    """Blender's factory startup file, emptied, with factory preferences. The bpy module reads
    no user preferences (it starts with the factory ones), so there only the file is read again:
    read_factory_settings would also re-register every add-on (~0.1 s of a run)."""
    if bpy.app.binary_path:     # the Blender executable: the user's preferences are loaded
        bpy.ops.wm.read_factory_settings(use_empty=True)
    else:
        bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)


@dataclass
class Inputs:
    source: object        # core.library.ExpressionLibrary
    target: files.Target
    landmarks: dict       # {"source": ids, "target": ids} or None (automatic)
    read: list            # every input file read (none may be overwritten)


def read_inputs(args, paths, timings, clone_process=None):
    """Source, target and landmarks, each checked; ExCloneError before any cloning. The source
    is read here, or by clone_process (CloneProcess: it has been reading it meanwhile)."""
    find_face = workflow.character_face
    if clone_process is None:
        clock = time.perf_counter()
        if not source_is_plain_files(args.source):  # the others are read by Blender
            empty_factory_scene()
        source = selected_shapes(files.load_source(args.source), args.shapes)
        timings["read_source"] = time.perf_counter() - clock
    else:   # the face it found, if it found it on this very object
        find_face = functools.partial(clone_process.face, find=workflow.character_face)
    clock = time.perf_counter()
    try:
        empty_factory_scene()  # the saved file holds only the target
        target = files.load_target(args.target, find_face)
        timings["read_target"] = time.perf_counter() - clock
    finally:
        if clone_process is not None:   # a bad source is the error reported, as if read first
            source, timings["read_source"] = clone_process.source()
    inputs = source_inputs(args.source) + [split_spec(args.target)[0] if args.target
                                           else data.DEMO_HEAD_FILE]
    landmarks = None
    if args.landmarks:
        landmarks = in_source_head(source, read_landmarks(
            Path(args.landmarks), source.own_vertex_count, len(target.mesh.vertices)))
        inputs.append(Path(args.landmarks))
    outputs = paths.files()
    if paths.export_dir is not None:
        outputs += export_paths(paths.export_dir, source.names).values()
    refuse_overwriting_inputs(outputs, inputs)
    refuse_replacing(outputs, args.overwrite)
    return Inputs(source, target, landmarks, inputs)


def write_outputs(outputs, paths, target, result, timings, landmarks, measures):
    """The target's new shape keys, saved (.blend, .glb or .fbx: files.save_result), exported
    as OBJs and rendered (unless --no-preview; with close-ups of the eyes and mouth placed by
    `landmarks`, {name: (3,) world point}, and chosen by `measures`); returns (added, replaced,
    skipped, exported paths or None, preview engine or None)."""
    clock = time.perf_counter()
    added, replaced, skipped = mesh_io.write_shape_keys(target.obj, result.names, result.deltas)
    followed = follow_face_keys(target, added, result)
    timings["write_shape_keys"] = time.perf_counter() - clock
    clock = time.perf_counter()
    outputs.write(paths.result, lambda path: files.save_result(path, target.objects))
    timings["save_result"] = time.perf_counter() - clock
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
            target.face.head.vertex_ids], added,            # framing the head
            preview.eye_and_mouth_close_ups(landmarks, measures, added))
        outputs.write(paths.preview, lambda path: _write_png(path, sheet))
        timings["preview"] = time.perf_counter() - clock
    return added, replaced, skipped, exported, engine, followed


def follow_face_keys(target, names, result):
    """The character's other objects (eyes, brows, lashes, teeth, tongue) get the face's new
    keys `names` as the operators give them (character_keys.follow_character); result's
    landmarks still in the head's numbering. Returns (the operators' clause, {object: the
    ExClone keys it holds})."""
    character_target = workflow.Target(target.objects, target.face, None)
    clause = character_keys.follow_character(character_target, names, result)
    keyed = {obj.name: len(set(obj.get(character_keys.MADE, [])) & set(names))
             for obj in character_target.others()}
    return clause, keyed


def build_report(args, paths, inputs, result, written, timings):
    source, target = inputs.source, inputs.target
    added, _, skipped, exported, engine, (followed, keyed) = written
    return {
        "inputs": {"source": source.description, "target": target.description,
                   "source_region": None if source.head is None else
                   f"head region: {len(source.head.vertex_ids):,} of {source.head.total:,} vertices",
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
        "outputs": {"result": str(paths.result), "report": str(paths.report),
                    "preview": str(paths.preview) if paths.preview else None,
                    "preview_engine": engine,
                    "export_dir": args.export_dir,
                    "exported_files": len(exported) if exported else 0,
                    "target_object": target.obj.name,
                    "shape_keys_added": added, "shape_keys_skipped_existing": skipped,
                    "other_objects": followed, "other_object_keys": keyed},
        "versions": {"blender": bpy.app.version_string, "numpy": np.__version__,
                     "python": platform.python_version()},
    }


def run(args, clone_process=None):
    """One target, everything the CLI does; returns the report (a dict), or None when --resume
    finds it done. ExCloneError on bad input or an output that cannot be written, and then no
    output is left behind. clone_process: a CloneProcess reading the source and cloning (else
    both are done here); the report's total time counts from its start, else from now."""
    started = time.perf_counter() if clone_process is None else clone_process.started
    paths = output_paths(args)
    if args.resume and paths.report.is_file():
        print(f"skipped: {paths.report} exists, the target is done (--resume)")
        return None
    timings = {}
    inputs = read_inputs(args, paths, timings, clone_process)
    # only the head of the face's object is solved, in world space (files.load_target)
    target = inputs.target
    face, landmarks = workflow.in_head(target.face, character.parts([target.obj])[0],
                                       inputs.landmarks)
    target.face = face
    if clone_process is None:
        done = cloned(inputs.source, face, landmarks, _print_progress())
    else:
        done = clone_process.clone(face, landmarks, _print_progress())
    result, measures, landmarks = done.result, done.measures, done.landmarks
    timings.update(done.timings)
    clock = time.perf_counter()
    # from here on, the face's object's own numbering and coordinates
    result.deltas = workflow.face_object_deltas(target.obj, face, result.deltas)
    timings["measures"] += time.perf_counter() - clock
    with Outputs() as outputs:
        written = write_outputs(outputs, paths, inputs.target, result, timings, landmarks,
                                measures)
        result.target_landmarks = face.head.own_ids(result.target_landmarks)
        result.source_landmarks = inputs.source.own_ids(result.source_landmarks)
        timings["total"] = time.perf_counter() - started
        report = build_report(args, paths, inputs, result, written, timings)
        report["measures"] = {"summary": summary(measures), "expressions": measures}
        _write_json(outputs, paths.report, report)
        outputs.commit()
    added, replaced, skipped, exported, _, (followed, _) = written
    print(f"result:  {paths.result}\nreport:  {paths.report}"
          + (f"\npreview: {paths.preview}" if paths.preview else "")
          + (f"\nexport:  {paths.export_dir} ({len(exported)} OBJs)" if exported else ""))
    print("measures: " + (reports.measures_clause(report["measures"]["summary"]) or "none"))
    rendered = f", preview {timings['preview']:.1f} s" if paths.preview else ""
    print(f"{target.face.description()}\n{target.obj.name}: "
          + reports.summary(added, replaced, skipped, timings["total"], result.quality)
          + f" (cloning {timings['clone_total']:.1f} s{rendered})"
          + (f"; {followed}" if followed else ""))
    return report


# -- several targets, each in its own process ----------------------------------------------------

def batch_targets(specs):
    """The --target values with each folder replaced by its mesh files (sorted by name)."""
    targets = []
    for spec in specs:
        path, _ = split_spec(spec)
        if not path.is_dir():
            targets.append(spec)
            continue
        found = sorted(p for p in path.iterdir()
                       if p.is_file() and p.suffix.lower() in TARGET_SUFFIXES)
        if not found:
            raise ExCloneError(f"target folder {path} holds no .blend, .obj, .fbx, .glb or "
                               ".gltf file")
        targets += [str(p) for p in found]
    return targets


def output_stems(targets):
    """One output name per target: the file's stem (and object), made unique with -2, -3..."""
    stems, seen = [], {}
    for spec in targets:
        path, name = split_spec(spec)
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


@dataclass
class BatchTarget:
    """One target of a batch and where its outputs go."""
    spec: str
    result: Path          # <out-dir>/<stem>_exclone.<format>
    export_dir: Path      # None without --export-dir

    @property
    def report(self):
        return self.result.with_suffix(".json")

    def done(self):
        """Finished in an earlier run: the report is moved into place last (run)."""
        return self.report.is_file()


def _entry(target, status, seconds, **fields):
    return {"target": target.spec, "status": status, "seconds": round(seconds, 2),
            "output": str(target.result), "report": str(target.report), **fields}


def _done_entry(target, seconds, status="done"):
    """A summary entry from the target's report on disk."""
    report = json.loads(target.report.read_text(encoding="utf-8"))
    return _entry(target, status, seconds, preview=report["outputs"]["preview"],
                  shape_keys_added=report["counts"]["shape_keys_added"],
                  fit_error_rel=report["quality"].get("registration_mean_distance_rel"))


def _run_target(command, target, shared_args, env, started):
    """This script on one target; returns its summary entry (never raises for a failed target).
    started(process) is called with the target's process as soon as it runs."""
    arguments = ["--target", target.spec, "--out", str(target.result)] + shared_args
    if target.export_dir is not None:
        arguments += ["--export-dir", str(target.export_dir)]
    clock = time.perf_counter()
    with subprocess.Popen(command + arguments, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True, env=env) as process:
        started(process)
        _, stderr = process.communicate()
    seconds = time.perf_counter() - clock
    if process.returncode != 0:
        lines = [line for line in stderr.splitlines() if line.strip()]
        error = lines[-1].removeprefix(f"{PROG}: error: ") if lines else \
            f"exited with code {process.returncode}"
        return _entry(target, "failed", seconds, error=error)
    return _done_entry(target, seconds)


def _batch_environment(jobs):
    env = dict(os.environ)
    if jobs > 1:  # the processes share the cores: one BLAS thread pool each, not one per core,
        for name in BLAS_THREADS:  # and no forked copy (clone_worker)
            env.setdefault(name, str(max(1, (os.cpu_count() or 1) // jobs)))
        env[ONE_PROCESS] = "1"
    return env


def available_memory():
    """Bytes of memory available to new processes now (Linux: MemAvailable, which counts the
    reclaimable cache; elsewhere the free pages), or None if the system does not say."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def estimated_vertices(spec):
    """A target's vertex count for sizing jobs: an OBJ's vertex lines, another file's size over
    FILE_BYTES_PER_VERTEX (an overestimate); 0 if it cannot be read (it will fail anyway)."""
    path = split_spec(spec)[0]
    try:
        if path.suffix.lower() == ".obj":
            with path.open("rb") as handle:
                return sum(1 for line in handle if line.startswith(b"v "))
        return path.stat().st_size // FILE_BYTES_PER_VERTEX
    except OSError:
        return 0


def plan_jobs(requested, n_targets, vertices, available, cpus):
    """(jobs, why): --jobs if given, else as many as the CPUs, the targets and the memory
    available allow, each job costing JOB_BASE_BYTES + JOB_BYTES_PER_VERTEX per vertex of the
    largest target (any of them may run beside the others). At least 1."""
    if requested is not None:
        return max(1, min(requested, n_targets)), "--jobs"
    per_job = JOB_BASE_BYTES + JOB_BYTES_PER_VERTEX * max(vertices, default=0)
    jobs = min(cpus, n_targets)
    why = f"{cpus} CPUs"
    if available is not None:
        fit = int(available * MEMORY_MARGIN // per_job)
        why += (f", {available / 1024 ** 3:.1f} GiB available, up to "
                f"{per_job / 1024 ** 3:.1f} GiB per target")
        jobs = min(jobs, fit)
    return max(1, jobs), why


def _batch_paths(args, specs):
    """(out_dir, summary path, [BatchTarget]), checked before any target runs."""
    out_dir = Path(args.out_dir or "out")
    summary_path = Path(args.report) if args.report else out_dir / "batch_report.json"
    if summary_path.suffix.lower() != ".json":
        raise ExCloneError(f"--report must name a .json file, got {summary_path}")
    refuse_overwriting_inputs([summary_path], [split_spec(t)[0] for t in specs
                                               if split_spec(t)[0].exists()])
    check_folder_writable(out_dir)
    check_output_writable(summary_path)
    if args.export_dir:
        check_folder_writable(args.export_dir)
    suffix = f".{args.format or 'blend'}"
    targets = [BatchTarget(spec, out_dir / f"{stem}_exclone{suffix}",
                           Path(args.export_dir) / stem if args.export_dir else None)
               for spec, stem in zip(specs, output_stems(specs))]
    return out_dir, summary_path, targets


def _refuse_replacing_batch(args, targets, summary_path):
    """Before any work: outputs of earlier runs are kept unless --overwrite; with --resume the
    done targets are skipped (and the summary rewritten), anything else is in the way."""
    if args.overwrite or args.summary_only:
        return
    in_the_way = [path for target in targets if not (args.resume and target.done())
                  for path in (target.result, target.report) if path.exists()]
    if summary_path.exists() and not args.resume:
        in_the_way.append(summary_path)
    if in_the_way:
        raise ExCloneError(f"{in_the_way[0]} exists ({len(in_the_way)} output(s) of an earlier "
                           "run in the way); give --resume to skip the targets that are done, or "
                           "--overwrite to replace them")


def _shared_arguments(args):
    shared = []
    for option, value in (("--source", args.source), ("--landmarks", args.landmarks),
                          ("--shapes", args.shapes)):
        if value is not None:
            shared += [option, value]
    for option, given in (("--no-preview", args.no_preview), ("--overwrite", args.overwrite)):
        if given:
            shared.append(option)
    return shared


def _console_line(index, count, entry):
    keys = entry.get("shape_keys_added")
    outcome = {"done": lambda: f"done, {keys} shape key{'' if keys == 1 else 's'}",
               "skipped": lambda: "skipped, done in an earlier run",
               "failed": lambda: f"FAILED: {entry['error']}"}[entry["status"]]()
    return f"[{index + 1}/{count}] {entry['target']}: {outcome} ({entry['seconds']:.1f} s)"


def _run_targets(args, targets):
    """Every target through this script in its own process, --jobs at a time (one bad or
    crashing target cannot stop the others); returns (summary entries in target order, jobs,
    interrupted: Ctrl-C, after which the targets not finished are failed "interrupted").
    --resume: done targets are skipped; --summary-only: nothing runs, a target without its
    report is failed."""
    entries = [None] * len(targets)
    pending = []
    for index, target in enumerate(targets):
        if args.summary_only:
            entries[index] = _done_entry(target, 0.0) if target.done() else _entry(
                target, "failed", 0.0, error="no report: its task did not finish (see its log)")
        elif args.resume and target.done():
            entries[index] = _done_entry(target, 0.0, status="skipped")
        else:
            pending.append(index)
    for index, entry in enumerate(entries):
        if entry is not None:
            print(_console_line(index, len(targets), entry), flush=True)
    if not pending:
        return entries, 0, False
    jobs, why = plan_jobs(args.jobs, len(pending),
                          [estimated_vertices(targets[i].spec) for i in pending],
                          available_memory(), os.cpu_count() or 1)
    print(f"batch: {len(pending)} target(s) to run, {jobs} at a time ({why})", flush=True)
    command, shared, env = _child_command(), _shared_arguments(args), _batch_environment(jobs)

    interrupted, lock, running, stopped = threading.Event(), threading.Lock(), {}, set()

    def started(index, process):
        with lock:
            running[index] = process
            if interrupted.is_set():
                process.terminate()

    def one(index):
        entry = _run_target(command, targets[index], shared, env,
                            lambda process: started(index, process))
        if entry["status"] == "failed" and interrupted.is_set():
            entry["error"] = "interrupted"     # whatever the process said as it was stopped
        entries[index] = entry
        with lock:
            running.pop(index, None)
        print(_console_line(index, len(targets), entry), flush=True)

    pool = ThreadPoolExecutor(max_workers=jobs)
    try:
        list(pool.map(one, pending))
    except KeyboardInterrupt:   # Ctrl-C: no new target starts; those running are stopped
        with lock:
            interrupted.set()
            stopped.update(running)
            # The terminal's Ctrl-C reached them too, but Blender's add-on loader swallows one
            # that lands while a process is still starting: that target would run to its end.
            for process in running.values():
                process.terminate()
        pool.shutdown(wait=True, cancel_futures=True)
        for index in pending:
            if entries[index] is None:
                entries[index] = _entry(targets[index], "failed", 0.0, error="interrupted")
            elif index in stopped and entries[index]["status"] == "failed":
                entries[index]["error"] = "interrupted"
        return entries, jobs, True
    pool.shutdown()
    return entries, jobs, False


def run_batch(args):
    """Every target (_run_targets), then the summary report; returns the summary. ExCloneError
    if any target failed or the batch was interrupted, after the summary was written."""
    started = time.perf_counter()
    specs = batch_targets(args.target)
    out_dir, summary_path, targets = _batch_paths(args, specs)
    _refuse_replacing_batch(args, targets, summary_path)
    entries, jobs, interrupted = _run_targets(args, targets)
    counts = {status: sum(entry["status"] == status for entry in entries)
              for status in ("done", "failed", "skipped")}
    summary = {"targets": entries, **counts, "jobs": jobs,
               "seconds": round(time.perf_counter() - started, 2),
               "arguments": {"source": args.source, "landmarks": args.landmarks,
                             "shapes": args.shapes, "no_preview": args.no_preview,
                             "format": args.format or "blend", "out_dir": str(out_dir),
                             "export_dir": args.export_dir, "resume": args.resume,
                             "overwrite": args.overwrite, "summary_only": args.summary_only}}
    with Outputs() as outputs:
        _write_json(outputs, summary_path, summary)
        outputs.commit()
    print(f"summary: {summary_path} ({counts['done']} done, {counts['failed']} failed, "
          f"{counts['skipped']} skipped, {summary['seconds']:.1f} s)")
    failed = [entry for entry in entries if entry["status"] == "failed"]
    if interrupted:
        raise ExCloneError(f"interrupted: {counts['done'] + counts['skipped']} of {len(entries)} "
                           "targets done; run the same command with --resume to continue; "
                           f"summary: {summary_path}")
    if failed:
        raise ExCloneError(f"{len(failed)} of {len(entries)} targets failed (first: "
                           f"{failed[0]['target']}: {failed[0]['error']}); the others were "
                           f"written; summary: {summary_path}")
    return summary


def main(argv, clone_process=None):
    """Run the CLI on argv (the arguments after the script); returns the exit code.
    clone_process: started_clone_process(argv)'s, stopped on return."""
    def work():
        args = parse_args(argv)
        if args.batch:
            run_batch(args)
        else:
            run(args, clone_process)

    with clone_process or contextlib.nullcontext():
        return run_main(PROG, work)


def _exit_now(code):
    """Exit without Blender's own teardown (freeing all its data, ~0.2 s of a run): every output
    is in place by now. Python's and the C library's buffered output is flushed first."""
    sys.stdout.flush()
    sys.stderr.flush()
    if os.name == "posix":
        ctypes.CDLL(None).fflush(None)
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    _exit_now(main(script_arguments(blender_executable=bool(bpy.app.binary_path)),
                   CLONE_PROCESS))
