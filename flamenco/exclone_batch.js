// SPDX-License-Identifier: GPL-3.0-or-later
//
// ExClone Batch: a Flamenco job type that clones facial expressions onto many heads at once,
// one task per target (scripts/batch_clone.py in Blender on any worker), then a summary task,
// after all of them, that writes <out_dir>/batch_report.json from the targets' reports.
//
// Put this file in the `scripts` folder next to the flamenco-manager executable and restart the
// Manager. The workers run "{blender}" (the Manager's variable) with "{exclone}/scripts/
// batch_clone.py": define the variable `exclone` in flamenco-manager.yaml as the folder holding
// the ExClone repository on each platform, and install and enable the ExClone extension in the
// workers' Blender (it brings scipy and OpenCV). Every path in the settings must be valid on the
// workers (shared storage).

const JOB_TYPE = {
    label: "ExClone Batch",
    description: "Clone facial expressions onto every target head, one task per target",
    settings: [
        { key: "targets", type: "string", required: true,
          description: "Target files separated by ';' (.obj, .fbx, .glb, .blend or .blend:Object)" },
        { key: "out_dir", type: "string", subtype: "dir_path", required: true,
          description: "Folder for each target's result and report, and the batch's summary" },
        { key: "source", type: "string", subtype: "file_path", default: "",
          description: "Expressions: a .blend/.fbx/.glb with shape keys or a folder of OBJs (empty: the bundled ARKit library)" },
        { key: "format", type: "string", choices: ["blend", "glb", "fbx"], default: "blend",
          description: "Each target's result file type" },
        { key: "shapes", type: "string", default: "",
          description: "Clone only these expressions, separated by ',' (empty: all)" },
        { key: "preview", type: "bool", default: false,
          description: "Render a contact sheet of each target's expressions (a few seconds each)" },
        { key: "overwrite", type: "bool", default: false,
          description: "Replace results that exist (otherwise a finished target is skipped)" },
        { key: "script", type: "string", default: "{exclone}/scripts/batch_clone.py", visible: "web",
          description: "batch_clone.py as the workers see it" },
    ],
};

const DEFAULT_SCRIPT = "{exclone}/scripts/batch_clone.py";
// Containers whose ':Object' suffix names an object inside the file.
const CONTAINERS = [".blend", ".fbx", ".glb", ".gltf"];

function compileJob(job) {
    const settings = job.settings;
    const targets = targetList(settings.targets);
    const stems = outputStems(targets);
    const shared = sharedArguments(settings);
    const format = settings.format || "blend";

    const summaryTask = author.Task("summary", "blender");
    for (let i = 0; i < targets.length; i++) {
        const out = path.join(settings.out_dir, `${stems[i]}_exclone.${format}`);
        const task = author.Task(`clone-${stems[i]}`, "blender");
        task.addCommand(exclone(settings, ["--target", targets[i], "--out", out, ...shared,
            settings.overwrite ? "--overwrite" : "--resume"]));
        job.addTask(task);
        summaryTask.addDependency(task);
    }
    const listed = targets.flatMap((target) => ["--target", target]);
    summaryTask.addCommand(exclone(settings, ["--summary-only", "--out-dir", settings.out_dir,
        "--format", format, ...listed]));
    job.addTask(summaryTask);
}

// batch_clone.py in Blender, in the background, with these arguments after "--".
function exclone(settings, args) {
    return author.Command("blender-render", {
        exe: "{blender}",
        exeArgs: "{blenderArgs}",
        argsBefore: [],
        blendfile: "",   // none: the script reads the target itself
        args: ["--python", settings.script || DEFAULT_SCRIPT, "--", ...args],
    });
}

function targetList(text) {
    const targets = (text || "").split(";").map((t) => t.trim()).filter((t) => t.length > 0);
    if (targets.length === 0) {
        throw "ExClone Batch: no targets; list the target files separated by ';'";
    }
    return targets;
}

function sharedArguments(settings) {
    const args = [];
    if (settings.source) args.push("--source", settings.source);
    if (settings.shapes) args.push("--shapes", settings.shapes);
    if (!settings.preview) args.push("--no-preview");
    return args;
}

// One output name per target, the rule of batch_clone.output_stems (the tests check both give
// the same names): the file's stem, "_Object" for a named object, characters other than
// letters, digits, '_', '.', '-' as '_', repeats numbered -2, -3...
function outputStems(targets) {
    const seen = {};
    return targets.map((target) => {
        const [file, object] = splitSpec(target);
        const base = file.split(/[\\/]/).pop();
        const dot = base.lastIndexOf(".");
        const fileStem = dot > 0 ? base.slice(0, dot) : base;
        const stem = (fileStem + (object ? `_${object}` : "")).replace(/[^A-Za-z0-9_.-]/g, "_");
        seen[stem] = (seen[stem] || 0) + 1;
        return seen[stem] === 1 ? stem : `${stem}-${seen[stem]}`;
    });
}

function splitSpec(target) {
    const colon = target.lastIndexOf(":");
    if (colon > 0) {
        const file = target.slice(0, colon);
        const object = target.slice(colon + 1);
        const lower = file.toLowerCase();
        if (object && CONTAINERS.some((suffix) => lower.endsWith(suffix))) {
            return [file, object];
        }
    }
    return [target, ""];
}
