"""Batch cloning from the command line; scripts/batch_clone.py is the entry point.

Runs inside the bpy module (`python scripts/batch_clone.py ARGS`) or Blender
(`blender -b --python scripts/batch_clone.py -- ARGS`). Input files are only read: OBJs with
core.mesh.read_obj (file coordinates and vertex order kept), .blend files by appending from them,
FBX/glTF with Blender's importers into an empty scene. Every output is a new file.
"""
import argparse
import json
import math
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

from .blender import mesh_io
from .cli import run_main
from .blender.operators import summary
from .core import data, library
from .core.cloning import CloneSettings, clone_expressions
from .core.errors import ExCloneError
from .core.mesh import MeshError, PolyMesh, check_mesh, read_obj, write_obj

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "batch_clone.py"
IMPORTERS = {".fbx": "fbx", ".glb": "gltf", ".gltf": "gltf"}
CONTAINERS = (".blend",) + tuple(IMPORTERS)
TARGET_SUFFIXES = (".obj",) + CONTAINERS
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# Contact sheet: the neutral plus the first of these that were cloned, then any others, 8 tiles.
PREVIEW_FAVOURITES = ("jawOpen", "eyeBlink_L", "mouthSmile_L", "browInnerUp", "browInnerUp_L",
                      "mouthPucker", "cheekPuff", "cheekPuff_L", "mouthFunnel", "browDown_R",
                      "noseSneer_L", "mouthFrown_L")
PREVIEW_TILES = 8
PREVIEW_SIZE = 320
MIN_LANDMARKS = 4


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise ExCloneError(message)


def parse_args(argv):
    parser = _Parser(
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
    parser.add_argument("--jobs", metavar="N", type=int, default=1,
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
    args = parser.parse_args(argv)
    targets = args.target or []
    args.batch = len(targets) > 1 or any(_split_spec(t)[0].is_dir() for t in targets)
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
        if args.jobs < 1:
            raise ExCloneError(f"--jobs must be at least 1, got {args.jobs}")
    return args


@dataclass
class Target:
    description: str
    mesh: PolyMesh
    obj: object                     # the bpy object that receives the shape keys
    inputs: list = field(default_factory=list)


def _split_spec(spec):
    """'file.blend:Object' -> (Path('file.blend'), 'Object'); anything else -> (Path, None)."""
    head, sep, name = spec.rpartition(":")
    if sep and Path(head).suffix.lower() in CONTAINERS and name and not Path(spec).exists():
        return Path(head), name
    return Path(spec), None


def _has_shape_keys(obj):
    return obj.data.shape_keys is not None and len(obj.data.shape_keys.key_blocks) > 1


def _objects_from_file(path):
    """Every object of a .blend (appended, not linked to a scene) or of an imported FBX/glTF."""
    if path.suffix.lower() == ".blend":
        try:
            with bpy.data.libraries.load(str(path), link=False) as (data_from, data_to):
                data_to.objects = list(data_from.objects)
        except OSError as exc:
            raise ExCloneError(f"{path} is not a readable .blend file") from exc
        return [obj for obj in data_to.objects if obj is not None]
    before = set(bpy.data.objects)
    importer = getattr(bpy.ops.import_scene, IMPORTERS[path.suffix.lower()])
    try:
        importer(filepath=str(path))
    except RuntimeError as exc:
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else "import failed"
        raise ExCloneError(f"cannot import {path}: {first_line}") from exc
    return [obj for obj in bpy.data.objects if obj not in before]


def _pick_object(path, name, role, need_shape_keys):
    """The named object, else the first mesh object (by name) - with shape keys for a source."""
    objects = sorted(_objects_from_file(path), key=lambda obj: obj.name)
    if name is not None:
        chosen = next((obj for obj in objects if obj.name == name), None)
        if chosen is None:
            available = ", ".join(obj.name for obj in objects[:10]) or "none"
            raise ExCloneError(f"{role} {path} has no object named '{name}' (objects: {available})")
        if chosen.type != 'MESH':
            raise ExCloneError(f"{role} {path}:{name} is not a mesh object")
        if need_shape_keys and not _has_shape_keys(chosen):
            raise ExCloneError(f"{role} {path}:{name} has no shape keys")
        return chosen
    meshes = [obj for obj in objects if obj.type == 'MESH']
    if not meshes:
        raise ExCloneError(f"{role} {path} contains no mesh object")
    if need_shape_keys:
        meshes = [obj for obj in meshes if _has_shape_keys(obj)]
        if not meshes:
            raise ExCloneError(f"{role} {path} has no mesh object with shape keys")
    return meshes[0]


def _existing(path, role):
    if not path.exists():
        raise ExCloneError(f"{role} not found: {path}")
    return path


def _checked(mesh, what):
    try:
        triangles = mesh.triangles()
    except MeshError as exc:
        raise MeshError(f"{what}: {exc}") from exc
    check_mesh(mesh.vertices, triangles, what=what)
    return mesh


def load_source(spec):
    """(ExpressionLibrary, description, input paths) for the --source argument."""
    if spec is None:
        source = library.load_library()
        description, inputs = f"bundled library {data.LIBRARY_FILE.name}", [
            data.LIBRARY_FILE]
    else:
        path, name = _split_spec(spec)
        _existing(path, "source")
        description = spec
        if path.is_dir():
            source = library.load_obj_folder(path)
            inputs = [path] + sorted(path.glob("*.obj"))
        elif path.suffix.lower() == ".obj":
            raise ExCloneError(f"source {path} is an OBJ file, which cannot hold shape keys: give "
                               "a folder with neutral.obj + one OBJ per expression, or a .blend, "
                               ".fbx or .glb mesh with shape keys")
        elif path.suffix.lower() in CONTAINERS:
            obj = _pick_object(path, name, "source", need_shape_keys=True)
            names, deltas = mesh_io.shape_keys_from_object(obj, what="source")
            source = library.ExpressionLibrary(mesh_io.mesh_from_object(obj, what="source"),
                                               names, deltas)
            description = f"{path}:{obj.name}"
            inputs = [path]
        else:
            raise ExCloneError(f"source {path}: unsupported file type '{path.suffix}' "
                               "(use .blend, .fbx, .glb or a folder of OBJs)")
    _checked(source.mesh, f"source {description}")
    if not source.names:
        raise ExCloneError(f"source {description} has no expressions")
    return source, description, inputs


def load_target(spec):
    """The target as a Target whose object sits in the current scene. An OBJ becomes a new
    object whose mesh keeps the file's coordinates, rotated +90 degrees about X (OBJ is Y-up)."""
    path, name = (data.DEMO_HEAD_FILE, None) if spec is None else _split_spec(spec)
    _existing(path, "target")
    suffix = path.suffix.lower()
    if path.is_dir():
        raise ExCloneError(f"target {path} is a folder; give a .blend, .obj, .fbx or .glb file")
    if suffix == ".obj":
        mesh = _checked(read_obj(path), f"target {path}")
        obj = mesh_io.object_from_mesh(path.stem, mesh)
        obj.rotation_euler = (math.pi / 2, 0.0, 0.0)
        return Target(str(path), mesh, obj, [path])
    if suffix not in CONTAINERS:
        raise ExCloneError(f"target {path}: unsupported file type '{path.suffix}' "
                           "(use .blend, .obj, .fbx or .glb)")
    obj = _pick_object(path, name, "target", need_shape_keys=False)
    description = f"{path}:{obj.name}"
    mesh = _checked(mesh_io.mesh_from_object(obj, what="target"), f"target {description}")
    # Keep only the target (and what it uses) in the file that will be saved.
    keep, ancestor = {obj}, obj.parent
    while ancestor is not None:
        keep.add(ancestor)
        ancestor = ancestor.parent
    bpy.data.batch_remove([other for other in bpy.data.objects if other not in keep])
    if obj.name not in bpy.context.scene.collection.all_objects:
        bpy.context.scene.collection.objects.link(obj)
    return Target(description, mesh, obj, [path])


def read_landmarks(path, n_source, n_target):
    """{"source": ids, "target": ids} from a JSON file, validated against both meshes."""
    _existing(path, "landmarks file")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ExCloneError(f"landmarks file {path} is not valid JSON ({exc})") from exc
    if not isinstance(data, dict) or not {"source", "target"} <= data.keys():
        raise ExCloneError(f'landmarks file {path} must be {{"source": [ids], "target": [ids]}}')
    ids = {}
    for side, n in (("source", n_source), ("target", n_target)):
        values = data[side]
        if not isinstance(values, list) or not all(
                isinstance(v, int) and not isinstance(v, bool) for v in values):
            raise ExCloneError(f"landmarks file {path}: '{side}' must be a list of vertex ids")
        bad = [v for v in values if not 0 <= v < n]
        if bad:
            raise ExCloneError(f"landmarks file {path}: {side} vertex id {bad[0]} is out of range "
                               f"(the {side} has {n} vertices, ids 0..{n - 1})")
        if len(set(values)) != len(values):
            raise ExCloneError(f"landmarks file {path}: {side} ids repeat a vertex")
        ids[side] = values
    if len(ids["source"]) != len(ids["target"]):
        raise ExCloneError(f"landmarks file {path}: {len(ids['source'])} source ids but "
                           f"{len(ids['target'])} target ids (they must pair up)")
    if len(ids["source"]) < MIN_LANDMARKS:
        raise ExCloneError(f"landmarks file {path}: {len(ids['source'])} pairs given, at least "
                           f"{MIN_LANDMARKS} are needed")
    return {side: np.array(values, dtype=np.int64) for side, values in ids.items()}


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


def export_shapes(directory, neutral, names, deltas):
    """Write neutral.obj and neutral + delta per name as OBJs (neutral's coordinates and order)."""
    Path(directory).mkdir(parents=True, exist_ok=True)
    paths = export_paths(directory, names)
    write_obj(paths["neutral"], neutral, header="ExClone: neutral")
    for name, delta in zip(names, deltas):
        shape = PolyMesh(neutral.vertices + delta, neutral.loop_totals, neutral.loop_vertices)
        write_obj(paths[name], shape, header=f"ExClone: shape key {name}")
    return paths


def _refuse_overwriting_inputs(outputs, inputs):
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


def _render_tile(scene, path):
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    import cv2
    image = cv2.imread(str(path))
    if image is None:
        raise ExCloneError(f"preview: rendering produced no image ({scene.render.engine})")
    return image


def _setup_preview_scene(scene, obj, vertices):
    """Orthographic front camera (looking along +Y, Blender's front view) framing the object."""
    matrix = np.array(obj.matrix_world)
    world = vertices @ matrix[:3, :3].T + matrix[:3, 3]
    low, high = world.min(axis=0), world.max(axis=0)
    center, size = (low + high) / 2, high - low
    camera = bpy.data.objects.new("ExClone preview camera", bpy.data.cameras.new("ExClone preview"))
    scene.collection.objects.link(camera)
    camera.data.type = 'ORTHO'
    camera.data.ortho_scale = 1.08 * max(size[0], size[2])
    camera.data.clip_end = 10 * (size.max() + 1)
    camera.location = (center[0], low[1] - 2 * size.max() - 0.1, center[2])
    camera.rotation_euler = (math.pi / 2, 0.0, 0.0)
    scene.camera = camera
    scene.render.resolution_x = scene.render.resolution_y = PREVIEW_SIZE
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = 'PNG'
    scene.world = bpy.data.worlds.new("ExClone preview")  # light grey background (and ambient)
    scene.world.color = (0.6, 0.6, 0.6)


def _use_cycles(scene):
    """CPU Cycles with few samples: the fallback when Workbench cannot render here."""
    scene.render.engine = 'CYCLES'
    scene.cycles.device = 'CPU'
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False
    scene.render.tile_size = 64
    sun = bpy.data.objects.new("ExClone preview sun", bpy.data.lights.new("ExClone sun", 'SUN'))
    sun.rotation_euler = (math.radians(60), 0.0, math.radians(-25))
    scene.collection.objects.link(sun)


def preview_names(names):
    favourites = [n for n in PREVIEW_FAVOURITES if n in names]
    others = [n for n in names if n not in favourites]
    return (favourites + others)[:PREVIEW_TILES - 1]


def render_preview(obj, vertices, names, path):
    """Contact sheet PNG: the neutral and up to 7 of the given shape keys, one label per tile.
    Returns the render engine used."""
    import cv2
    scene = bpy.context.scene
    _setup_preview_scene(scene, obj, vertices)
    key_blocks = obj.data.shape_keys.key_blocks
    shown = ["neutral"] + preview_names(names)
    scene.render.engine = 'BLENDER_WORKBENCH'
    tiles = []
    with tempfile.TemporaryDirectory(prefix="exclone_preview_") as tmp:
        for i, name in enumerate(shown):
            for block in key_blocks[1:]:
                block.value = 1.0 if block.name == name else 0.0
            tile_path = Path(tmp) / f"{i}.png"
            try:
                tile = _render_tile(scene, tile_path)
            except RuntimeError:
                tile = None
            if i == 0 and scene.render.engine == 'BLENDER_WORKBENCH' and (
                    tile is None or tile.std() < 1.0):
                _use_cycles(scene)
                tile = _render_tile(scene, tile_path)
            if tile is None:
                raise ExCloneError(f"preview: {scene.render.engine} could not render")
            tiles.append(tile)
    for block in key_blocks[1:]:
        block.value = 0.0
    blank = np.full_like(tiles[0], 255)
    tiles += [blank] * (-len(tiles) % 4)
    for tile, name in zip(tiles, shown):
        for colour, thickness in (((255, 255, 255), 3), ((0, 0, 0), 1)):
            cv2.putText(tile, name, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, thickness,
                        cv2.LINE_AA)
    rows = [np.hstack(tiles[r:r + 4]) for r in range(0, len(tiles), 4)]
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.vstack(rows)):
        raise ExCloneError(f"cannot write the preview {path}")
    return scene.render.engine


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
    if isinstance(value, (np.ndarray, Path)):
        return value.tolist() if isinstance(value, np.ndarray) else str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def run(args):
    """Everything the CLI does; returns the report (a dict). Raises ExCloneError on bad input."""
    started = time.perf_counter()
    target_file = data.DEMO_HEAD_FILE if args.target is None else _split_spec(args.target)[0]
    out = Path(args.out) if args.out else Path("out") / f"{target_file.stem}_exclone.blend"
    if out.suffix.lower() != ".blend":
        raise ExCloneError(f"--out must name a .blend file, got {out}")
    report_path = Path(args.report) if args.report else out.with_suffix(".json")
    preview_path = Path(args.preview) if args.preview else out.with_suffix(".png")
    if preview_path.suffix.lower() != ".png":
        raise ExCloneError(f"--preview must name a .png file, got {preview_path}")

    timings = {}
    clock = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    source, source_description, inputs = load_source(args.source)
    if args.shapes is not None:
        wanted = list(dict.fromkeys(name.strip() for name in args.shapes.split(",")
                                    if name.strip()))
        if not wanted:
            raise ExCloneError("--shapes names no expression")
        unknown = [name for name in wanted if name not in source.names]
        if unknown:
            raise ExCloneError(f"unknown expression(s) {', '.join(unknown)}; available: "
                               f"{', '.join(source.names[:6])}, ... ({len(source.names)} in all)")
        source = source.subset(wanted)
    timings["read_source"] = time.perf_counter() - clock

    clock = time.perf_counter()
    bpy.ops.wm.read_factory_settings(use_empty=True)  # the saved file holds only the target
    target = load_target(args.target)
    inputs += target.inputs
    timings["read_target"] = time.perf_counter() - clock
    landmarks = None
    if args.landmarks:
        landmarks = read_landmarks(Path(args.landmarks), len(source.mesh.vertices),
                                   len(target.mesh.vertices))
        inputs.append(Path(args.landmarks))
    outputs = [out, report_path, preview_path]
    if args.export_dir:
        outputs += export_paths(args.export_dir, source.names).values()
    _refuse_overwriting_inputs(outputs, inputs)

    clock = time.perf_counter()
    result = clone_expressions(source.mesh, source.deltas, source.names, target.mesh,
                               landmarks=landmarks, source_landmarks=source.automatic_landmarks,
                               settings=CloneSettings(), progress=_print_progress())
    timings.update({f"clone_{phase}": seconds for phase, seconds in result.timings.items()})
    timings["clone_total"] = time.perf_counter() - clock

    clock = time.perf_counter()
    added, replaced, skipped = mesh_io.write_shape_keys(target.obj, result.names, result.deltas)
    timings["write_shape_keys"] = time.perf_counter() - clock
    clock = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(out.resolve()), copy=True, check_existing=False)
    timings["save_blend"] = time.perf_counter() - clock
    exported = None
    if args.export_dir:
        clock = time.perf_counter()
        rows = [result.names.index(name) for name in added]
        exported = export_shapes(args.export_dir, target.mesh, added, result.deltas[rows])
        timings["export_obj"] = time.perf_counter() - clock
    clock = time.perf_counter()
    preview_engine = render_preview(target.obj, target.mesh.vertices, added, preview_path)
    timings["preview"] = time.perf_counter() - clock
    timings["total"] = time.perf_counter() - started

    source_triangles = len(source.mesh.triangles())
    report = {
        "inputs": {"source": source_description, "target": target.description,
                   "landmarks": args.landmarks, "shapes": args.shapes},
        "counts": {"source_vertices": len(source.mesh.vertices),
                   "source_triangles": source_triangles,
                   "target_vertices": len(target.mesh.vertices),
                   "target_triangles": len(target.mesh.triangles()),
                   "expressions": len(result.names), "shape_keys_added": len(added),
                   "shape_keys_skipped": len(skipped)},
        "timings": timings,
        "quality": result.quality,
        "landmarks": {"source": result.source_landmarks, "target": result.target_landmarks,
                      "names": list(result.landmark_names),
                      "automatic": landmarks is None},
        "outputs": {"blend": str(out), "report": str(report_path), "preview": str(preview_path),
                    "preview_engine": preview_engine,
                    "export_dir": args.export_dir,
                    "exported_files": len(exported) if exported else 0,
                    "target_object": target.obj.name,
                    "shape_keys_added": added, "shape_keys_skipped_existing": skipped},
        "versions": {"blender": bpy.app.version_string, "numpy": np.__version__,
                     "python": platform.python_version()},
    }
    report_path.parent.mkdir(parents=True, exist_ok=True)
    report_path.write_text(json.dumps(report, indent=2, default=_json_value) + "\n",
                           encoding="utf-8")
    print(f"blend:   {out}\nreport:  {report_path}\npreview: {preview_path}"
          + (f"\nexport:  {args.export_dir} ({len(exported)} OBJs)" if exported else ""))
    print(f"{target.obj.name}: " + summary(added, replaced, skipped, timings["total"],
                                          result.quality)
          + f" (cloning {timings['clone_total']:.1f} s, preview {timings['preview']:.1f} s)")
    return report


def batch_targets(specs):
    """The --target values with each folder replaced by its mesh files (sorted by name)."""
    targets = []
    for spec in specs:
        path, _ = _split_spec(spec)
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
        path, name = _split_spec(spec)
        stem = _file_stem(path.stem + (f"_{name}" if name else ""))
        seen[stem] = seen.get(stem, 0) + 1
        stems.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return stems


def _child_command():
    """How to run the single-target CLI in a new process, here: the bpy module's Python or
    the Blender executable."""
    if not SCRIPT.is_file():
        raise ExCloneError(f"batches run {SCRIPT} once per target, and it is missing")
    if bpy.app.binary_path:
        return [bpy.app.binary_path, "-b", "--python", str(SCRIPT), "--"]
    return [sys.executable, str(SCRIPT)]


def _run_target(command, spec, out, shared_args, env, export_dir):
    """The single-target CLI on one target; returns its summary entry (never raises for a
    failed target)."""
    arguments = ["--target", spec, "--out", str(out)] + shared_args
    if export_dir is not None:
        arguments += ["--export-dir", str(export_dir)]
    clock = time.perf_counter()
    done = subprocess.run(command + arguments, capture_output=True, text=True, env=env)
    entry = {"target": spec, "seconds": round(time.perf_counter() - clock, 2)}
    if done.returncode != 0:
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        error = lines[-1].removeprefix("batch_clone: error: ") if lines else \
            f"exited with code {done.returncode}"
        entry.update(status="failed", error=error)
        return entry
    report = json.loads(out.with_suffix(".json").read_text(encoding="utf-8"))
    entry.update(status="ok", blend=str(out), report=str(out.with_suffix(".json")),
                 preview=str(out.with_suffix(".png")),
                 shape_keys_added=report["counts"]["shape_keys_added"],
                 fit_error_rel=report["quality"].get("registration_mean_distance_rel"))
    return entry


def run_batch(args):
    """Every target through the single-target CLI, --jobs at a time, each in its own process (one
    bad or crashing target cannot stop the others). Writes the summary report and returns it."""
    started = time.perf_counter()
    targets = batch_targets(args.target)
    out_dir = Path(args.out_dir or "out")
    summary_path = Path(args.report) if args.report else out_dir / "batch_report.json"
    if summary_path.suffix.lower() != ".json":
        raise ExCloneError(f"--report must name a .json file, got {summary_path}")
    _refuse_overwriting_inputs([summary_path], [_split_spec(t)[0] for t in targets
                                                if _split_spec(t)[0].exists()])
    command = _child_command()
    shared = []
    for option, value in (("--source", args.source), ("--landmarks", args.landmarks),
                          ("--shapes", args.shapes)):
        if value is not None:
            shared += [option, value]
    jobs = min(args.jobs, len(targets))
    env = dict(os.environ)
    if jobs > 1:  # the processes share the cores: one BLAS thread pool each, not one per core
        for name in BLAS_THREADS:
            env.setdefault(name, str(max(1, (os.cpu_count() or 1) // jobs)))
    stems = output_stems(targets)
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
        entries = list(pool.map(one, range(len(targets))))
    failed = [entry for entry in entries if entry["status"] != "ok"]
    summary = {"targets": entries, "succeeded": len(entries) - len(failed), "failed": len(failed),
               "jobs": jobs, "seconds": round(time.perf_counter() - started, 2),
               "arguments": {"source": args.source, "landmarks": args.landmarks,
                             "shapes": args.shapes, "out_dir": str(out_dir),
                             "export_dir": args.export_dir}}
    summary_path.parent.mkdir(parents=True, exist_ok=True)
    summary_path.write_text(json.dumps(summary, indent=2, default=_json_value) + "\n",
                            encoding="utf-8")
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

    return run_main("batch_clone", work)
