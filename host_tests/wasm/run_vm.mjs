// Runs Python code on the WebAssembly build of MicroPython, with the firmware package
// and the host-side helpers on the VM's filesystem:
//   /lib/jig/*.py                    firmware/jig (the code under test, unchanged)
//   /lib/capture_format.py, /lib/vm_probe.py
//   /captures/*.cap                  host_tests/captures
//   /data/<name>                     files given with --file NAME=PATH
//
// usage: node run_vm.mjs [--file NAME=PATH]... CODE
// Prints what the code prints; exits 1 with the Python traceback on an exception,
// 2 on a usage error.

import fs from "node:fs";
import path from "node:path";
import { fileURLToPath } from "node:url";

const here = path.dirname(fileURLToPath(import.meta.url));
const root = path.resolve(here, "..", "..");

function usage(msg) {
  if (msg) process.stderr.write(`run_vm: ${msg}\n`);
  process.stderr.write("usage: node run_vm.mjs [--file NAME=PATH]... CODE\n");
  process.exit(2);
}

const args = process.argv.slice(2);
const extra = [];
let code = null;
for (let i = 0; i < args.length; i++) {
  if (args[i] === "--help" || args[i] === "-h") {
    process.stdout.write("usage: node run_vm.mjs [--file NAME=PATH]... CODE\n" +
      "Runs CODE on MicroPython (WebAssembly) with firmware/jig, the capture helpers and the captures loaded.\n");
    process.exit(0);
  } else if (args[i] === "--file") {
    const spec = args[++i] || "";
    const eq = spec.indexOf("=");
    if (eq <= 0) usage("--file needs NAME=PATH");
    extra.push([spec.slice(0, eq), spec.slice(eq + 1)]);
  } else if (code === null) {
    code = args[i];
  } else {
    usage("more than one CODE argument");
  }
}
if (code === null) usage("no CODE given");

let loadMicroPython;
try {
  ({ loadMicroPython } = await import(
    "@micropython/micropython-webassembly-pyscript"
  ));
} catch (e) {
  process.stderr.write("run_vm: the MicroPython WebAssembly package is not installed (run tools/setup.sh)\n");
  process.exit(3);
}

const out = [];
const mp = await loadMicroPython({
  heapsize: 8 * 1024 * 1024,
  stdout: (line) => process.stdout.write(line + "\n"),
  stderr: (line) => out.push(line),
});

function copyDir(src, dst, ext) {
  mp.FS.mkdirTree(dst);
  for (const name of fs.readdirSync(src).sort()) {
    if (name.endsWith(ext)) mp.FS.writeFile(`${dst}/${name}`, fs.readFileSync(path.join(src, name)));
  }
}

copyDir(path.join(root, "firmware", "jig"), "/lib/jig", ".py");
for (const name of ["capture_format.py", "vm_probe.py"]) {
  mp.FS.writeFile(`/lib/${name}`, fs.readFileSync(path.join(root, "host_tests", name)));
}
copyDir(path.join(root, "host_tests", "captures"), "/captures", ".cap");
mp.FS.mkdirTree("/data");
for (const [name, file] of extra) {
  try {
    mp.FS.writeFile(`/data/${name}`, fs.readFileSync(file));
  } catch (e) {
    process.stderr.write(`run_vm: cannot read ${file}: ${e.message}\n`);
    process.exit(2);
  }
}

try {
  mp.runPython("import sys\nsys.path.insert(0, '/lib')\n" + code);
} catch (e) {
  process.stderr.write(out.join("\n") + "\n" + String(e && e.message ? e.message : e) + "\n");
  process.exit(1);
}
if (out.length) process.stderr.write(out.join("\n") + "\n");
