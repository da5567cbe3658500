// Runs a Flamenco job compiler script the way the Manager does, outside it: the script is
// evaluated with the documented globals of the job-compiler interface (author.Task,
// author.Command, print, path), its compileJob(job) is called with a job of the given
// settings, and the tasks it added are printed as JSON.
//
//     node flamenco_compile.js SCRIPT.js SETTINGS.json
//
// Output: {"job_type": JOB_TYPE, "tasks": [{name, type, commands: [{name, parameters}],
// dependencies: [task names]}]}; a compile error (the script throws) exits 2 with the error.
"use strict";
const fs = require("fs");
const nodePath = require("path");
const vm = require("vm");

const [scriptFile, settingsFile] = process.argv.slice(2);
const tasks = [];

const author = {
    Task(name, type) {
        const task = { name, type, commands: [], dependencies: [] };
        task.addCommand = (command) => { task.commands.push(command); };
        task.addDependency = (other) => { task.dependencies.push(other); };
        return task;
    },
    Command(name, parameters) {
        return { name, parameters };
    },
};
// the path helpers Flamenco's own job types use (POSIX paths, as on the Linux workers)
const path = {
    join: (...parts) => nodePath.posix.join(...parts),
    basename: (p) => nodePath.posix.basename(p),
    dirname: (p) => nodePath.posix.dirname(p),
    stem: (p) => nodePath.posix.parse(p).name,
};
const job = {
    name: "test job",
    settings: JSON.parse(fs.readFileSync(settingsFile, "utf8")),
    addTask(task) { tasks.push(task); },
};
const context = vm.createContext({ author, path, print: (...a) => console.error(...a) });
vm.runInContext(fs.readFileSync(scriptFile, "utf8") + "\n;globalThis.JOB_TYPE = JOB_TYPE;",
                context, { filename: scriptFile });
try {
    context.compileJob(job);
} catch (error) {
    console.log(JSON.stringify({ error: String(error) }));
    process.exit(2);
}
console.log(JSON.stringify({
    job_type: context.JOB_TYPE,
    tasks: tasks.map((task) => ({
        name: task.name, type: task.type, commands: task.commands,
        dependencies: task.dependencies.map((other) => other.name),
    })),
}));
